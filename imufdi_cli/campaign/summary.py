"""Run results -> runs.csv rows, summary groups over seeds, curves, Markdown, gates."""

from __future__ import annotations

import csv
import io
import json
import os
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from imufdi_cli.campaign.spec import CampaignSpec
from imufdi_cli.errors import ImufdiError
from imufdi_cli.metrics import (
    METRIC_NAMES,
    mean_metrics,
)

_AMPLITUDE_KEYS = ("amp", "rate", "factor", "sigma")


def _fault_model_amp(specs: Sequence[str]) -> tuple[str, str]:
    """Model and amplitude-like parameter of a run's (first) fault spec, for grouping."""
    spec = specs[0]
    model, rest = spec.split(":", 1)
    parts = rest.split(",")
    values = dict(p.split("=", 1) for p in parts[1:] if "=" in p)
    amp = next((values[k] for k in _AMPLITUDE_KEYS if values.get(k)), "")
    return model, amp


def _fault_label(specs: Sequence[str]) -> tuple[str, str]:
    """The run's (first) fault spec without its amplitude, and its sensor: runs that differ
    only in amplitude share the label (one curve), faults on different sensors do not."""
    spec = specs[0]
    head, *items = spec.split(",")
    kept = [it for it in items if it.split("=", 1)[0] not in _AMPLITUDE_KEYS]
    sensor = head.split(":", 1)[1] if ":" in head else ""
    return ",".join([head, *kept]), sensor


def _amplitude_number(amplitude: str) -> tuple[float | None, str]:
    """``"0.9deg/s"`` -> ``(0.9, "deg/s")``: the spec's number and unit as written."""
    import re

    match = re.match(r"^\s*([+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)\s*(.*?)\s*$", amplitude)
    if not match:
        return None, ""
    return float(match.group(1)), match.group(2)


def _base_label(base: Mapping[str, Any]) -> str:
    if "preset" in base:
        opts = ",".join(f"{k}={v}" for k, v in sorted(base.get("options", {}).items()))
        return base["preset"] + (f"[{opts}]" if opts else "")
    return os.path.basename(base["file"])


def _rows(results: Iterable[Mapping[str, Any]]) -> list[dict[str, Any]]:
    rows = []
    for r in results:
        run = r["run"]
        model, amp = _fault_model_amp(run["faults"])
        label, sensor = _fault_label(run["faults"])
        onsets: list[Any] = []
        if r["ok"]:
            first: Mapping[str, Any] = next(iter(r["metrics"].values()), {})
            onsets = first.get("onsets_s") or []
        common = {
            "key": r["key"],
            "base": _base_label(run["base"]),
            "seed": run["seed"],
            "faults": ";".join(run["faults"]),
            "fault": label,
            "sensor": sensor,
            "onset_s": ";".join("" if o is None else f"{o:.6f}" for o in onsets),
            "model": model,
            "amplitude": amp,
            "detector": run["detector"],
            "params": json.dumps(run["params"], sort_keys=True),
            "ok": r["ok"],
            "error": r.get("error", ""),
        }
        if not r["ok"]:
            rows.append(common | {"sensor_type": ""})
            continue
        for sensor_type, figures in sorted(r["metrics"].items()):
            row = common | {"sensor_type": sensor_type}
            row |= {name: figures.get(name) for name in METRIC_NAMES}
            row["target_far"] = figures.get("target_far")
            rows.append(row)
    return rows


def _rows_csv(rows: Sequence[Mapping[str, Any]]) -> str:
    fields = [
        "key",
        "base",
        "seed",
        "faults",
        "fault",
        "sensor",
        "onset_s",
        "model",
        "amplitude",
        "detector",
        "params",
        "sensor_type",
        "ok",
        "error",
        *METRIC_NAMES,
        "target_far",
    ]
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=fields, lineterminator="\n")
    writer.writeheader()
    for row in sorted(
        rows,
        key=lambda r: (
            r["base"],
            r["detector"],
            r["params"],
            r["faults"],
            r["seed"],
            r["sensor_type"],
        ),
    ):
        writer.writerow({k: ("" if row.get(k) is None else row.get(k)) for k in fields})
    return buffer.getvalue()


def _amplitude_order(amplitude: str, sensor_type: str) -> tuple[bool, float, str]:
    si = _amplitude_si(amplitude, sensor_type)
    return (si is None, 0.0 if si is None else si, amplitude)


def summarize(spec: CampaignSpec, results: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Means and spreads over seeds per base x detector x params x fault (spec without its
    amplitude, so faults on different sensors stay apart) x amplitude x sensor type,
    amplitudes in numeric order, plus detection probability against amplitude."""
    groups: dict[tuple[str, ...], list[dict[str, Any]]] = {}
    for row in _rows(results):
        if not row["ok"]:
            continue
        sensor = row["sensor"].split(".")
        fault_type = sensor[1] if len(sensor) > 1 else ""
        if row["sensor_type"] != fault_type:
            continue  # score each run on the sensor type its fault acts on
        key = (
            row["base"],
            row["detector"],
            row["params"],
            row["fault"],
            row["amplitude"],
            row["sensor_type"],
        )
        groups.setdefault(key, []).append(row)
    table = []
    ordered = sorted(
        groups.items(),
        key=lambda item: (item[0][:4], item[0][5], _amplitude_order(item[0][4], item[0][5])),
    )
    for (base, det, params, fault, amp, sensor_type), rows in ordered:
        first = rows[0]
        entry: dict[str, Any] = {
            "base": base,
            "detector": det,
            "params": json.loads(params),
            "fault": fault,
            "sensor": first["sensor"],
            "model": first["model"],
            "amplitude": amp,
            "sensor_type": sensor_type,
            "runs": len(rows),
        }
        for metric in spec.metrics:
            mean, std, count = mean_metrics([r.get(metric) for r in rows])
            entry[metric] = {"mean": mean, "std": std, "n": count}
        targets = {float(r["target_far"]) for r in rows if r.get("target_far") is not None}
        if targets:
            entry["target_far"] = sorted(targets)[0]
        table.append(entry)
    failures = [{"key": r["key"], "error": r.get("error", "")} for r in results if not r["ok"]]
    return {
        "name": spec.name,
        "spec": spec.source,
        "runs": len(results),
        "failed": len(failures),
        "metrics": spec.metrics,
        "groups": table,
        "curves": detection_curves(table),
        "failures": failures[:50],
    }


def _amplitude_si(amplitude: str, sensor_type: str) -> float | None:
    """Amplitude text -> SI float (``"0.9deg/s"`` on gyro -> rad/s); bare numbers as is."""
    from imufdi_cli.units import parse_quantity, rate_dimension, sensor_dimension

    for dimension in (sensor_dimension, rate_dimension):  # amplitudes, then drift rates
        try:
            return float(parse_quantity(amplitude, dimension(sensor_type)))
        except ImufdiError:
            continue
    try:
        return float(amplitude)
    except ValueError:
        return None


def detection_curves(groups: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Detection probability against amplitude, one curve per base x detector x params x
    fault (spec without amplitude) x sensor type, points sorted by SI amplitude and given
    in the spec's own units too (``amplitude_value``, ``unit`` when all points share one)."""
    curves: dict[tuple[str, str, str, str, str], list[dict[str, Any]]] = {}
    models: dict[tuple[str, str, str, str, str], str] = {}
    for g in groups:
        stat = g.get("detection_probability")
        if stat is None:
            continue
        fault = g.get("fault", g["model"])
        key = (
            g["base"],
            g["detector"],
            json.dumps(g["params"], sort_keys=True),
            fault,
            g["sensor_type"],
        )
        models[key] = g["model"]
        value, unit = _amplitude_number(g["amplitude"])
        curves.setdefault(key, []).append(
            {
                "amplitude": g["amplitude"],
                "amplitude_si": _amplitude_si(g["amplitude"], g["sensor_type"]),
                "amplitude_value": value,
                "amplitude_unit": unit,
                "mean": stat["mean"],
                "std": stat["std"],
                "n": stat["n"],
            }
        )
    out = []
    for key, points in sorted(curves.items()):
        base, det, params, fault, sensor_type = key
        points.sort(key=lambda p: (p["amplitude_si"] is None, p["amplitude_si"] or 0.0))
        units = {p["amplitude_unit"] for p in points}
        out.append(
            {
                "base": base,
                "detector": det,
                "params": json.loads(params),
                "fault": fault,
                "model": models[key],
                "sensor_type": sensor_type,
                "unit": units.pop() if len(units) == 1 else None,
                "points": points,
            }
        )
    return out


#: Metrics that are rates, shown in % in summary.md.
PERCENT_METRICS = frozenset(
    {
        "far",
        "mar",
        "accuracy",
        "fir",
        "isolation_accuracy",
        "detection_rate",
        "detection_probability",
        "alarm_rate",
        "far_calibration",
        "rate_after_first_detection",
        "mar_at_far",
        "fir_at_far",
    }
)


def summary_markdown(summary: Mapping[str, Any]) -> str:
    """``summary.md``: the groups as a Markdown table (rates in %, mean ± std over seeds),
    the detection-probability curves, and the failed runs."""
    lines = [
        f"# Campaign {summary['name']}",
        "",
        f"{summary['runs']} runs, {summary['failed']} failed. Mean ± standard deviation over seeds.",
        "FAR outside the calibration window; delays at decision time; `*_at_far` with the"
        " threshold scaled to the matched FAR"
        + (
            f" ({100 * summary['groups'][0]['target_far']:g} %)."
            if summary["groups"] and "target_far" in summary["groups"][0]
            else "."
        ),
        "",
        *_groups_table(summary["groups"], summary["metrics"]),
    ]
    curves = summary.get("curves") or []
    if curves:
        lines += ["", "## Detection probability against amplitude", "", *_curves_table(curves)]
    if summary["failures"]:
        lines += ["", "## Failed runs", ""]
        lines += [f"- `{f['key']}`: {f['error']}" for f in summary["failures"]]
    return "\n".join(lines) + "\n"


def _params_text(params: Mapping[str, Any]) -> str:
    return ", ".join(f"{k}={v}" for k, v in params.items()) or "default"


def _groups_table(groups: Sequence[Mapping[str, Any]], metrics: Sequence[str]) -> list[str]:
    scale = {m: 100.0 if m in PERCENT_METRICS else 1.0 for m in metrics}
    head = ["base", "detector", "params", "fault", "amplitude", "type", "runs"] + [
        f"{m} {'%' if scale[m] == 100.0 else ''}".strip() for m in metrics
    ]
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
    for g in groups:
        cells = [
            g["base"],
            g["detector"],
            _params_text(g["params"]),
            g.get("fault", g["model"]),
            g["amplitude"],
            g["sensor_type"],
            str(g["runs"]),
        ]
        for m in metrics:
            stat = g[m]
            if stat["mean"] is None:
                cells.append("undefined")
            elif stat["std"] is None:
                cells.append(f"{stat['mean'] * scale[m]:.3g}")
            else:
                cells.append(f"{stat['mean'] * scale[m]:.3g} ± {stat['std'] * scale[m]:.2g}")
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def _curves_table(curves: Sequence[Mapping[str, Any]]) -> list[str]:
    lines = [
        "| base | detector | params | fault | type | amplitude: probability % |",
        "|---|---|---|---|---|---|",
    ]
    for c in curves:
        points = ", ".join(
            f"{p['amplitude'] or '-'}: "
            + ("undefined" if p["mean"] is None else f"{100.0 * p['mean']:.3g}")
            for p in c["points"]
        )
        lines.append(
            f"| {c['base']} | {c['detector']} | {_params_text(c['params'])}"
            f" | {c.get('fault', c['model'])} | {c['sensor_type']} | {points} |"
        )
    return lines


def evaluate_summary_gates(
    summary: Mapping[str, Any], gates: Sequence[str]
) -> list[tuple[str, bool, str]]:
    """``DETECTOR.TYPE.METRIC OP NUMBER`` on the group means; a gate fails when any group
    of that detector and type violates it (or its mean is undefined)."""
    from imufdi_cli.detectors import DETECTORS
    from imufdi_cli.errors import GateError
    from imufdi_cli.report import OPERATORS, parse_gate

    parsed = [parse_gate(g, DETECTORS) for g in gates]
    outcomes = []
    for gate in parsed:
        groups = [
            g
            for g in summary["groups"]
            if gate.detector in ("*", g["detector"]) and gate.sensor_type in ("*", g["sensor_type"])
        ]
        if not groups:
            raise GateError(
                f"--fail-if {gate.text!r}: no campaign results for {gate.detector}.{gate.sensor_type}"
            )
        for g in groups:
            stat = g.get(gate.metric)
            if stat is None:
                raise GateError(
                    f"--fail-if {gate.text!r}: metric {gate.metric!r} is not aggregated; add it to campaign.metrics"
                )
            label = f"{g['detector']}.{g['sensor_type']}.{gate.metric} [{g['base']} {g['model']} {g['amplitude']}]"
            if stat["mean"] is None:
                outcomes.append((label, True, f"{label} is undefined"))
                continue
            failed = OPERATORS[gate.op](stat["mean"], gate.value)
            outcomes.append(
                (
                    label,
                    failed,
                    f"{'FAILED' if failed else 'passed'}: {label} = {stat['mean']:.6g} (fail if {gate.op} {gate.value:g})",
                )
            )
    return outcomes
