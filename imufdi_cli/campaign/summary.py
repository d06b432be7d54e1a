"""Run results -> runs.csv rows, summary groups over seeds, curves, Markdown, gates."""

from __future__ import annotations

import csv
import io
import json
import os
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

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
            "params": json.dumps(run_params(run), sort_keys=True),
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
            row["target_budget_per_hour"] = figures.get("target_budget_per_hour")
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


#: Figures pooled over a group's runs (counts and hours summed, then the rate and its
#: bounds): a single run holds minutes of fault-free time, far too little for a rate of a
#: few false episodes an hour.
POOLED_METRICS = (
    "false_episodes",
    "fault_free_hours",
    "false_episodes_per_hour",
    "false_episodes_per_hour_upper95",
    "mtbfa_h",
    "mtbfa_h_lower95",
)
#: Figures of each run at the budget matched over all the runs of its detector (and
#: parameters) on its sensor type, then averaged over a group's runs like the others.
BUDGET_METRICS = (
    "mar_at_budget",
    "fir_at_budget",
    "detection_delay_s_at_budget",
    "isolation_delay_s_at_budget",
    "reference_delay_s",
    "delay_ratio",
)


def run_params(run: Mapping[str, Any]) -> dict[str, Any]:
    """A run's detector parameters as it ran: its ``params`` and, when the campaign or its
    [[detector]] gave one, the false-alarm budget (``false_alarms = "1/h"``)."""
    params = dict(run["params"])
    if run.get("false_alarms") is not None:
        params.setdefault("false_alarms", f"{float(run['false_alarms']) * 3600:g}/h")
    return params


def _pool_key(run: Mapping[str, Any], sensor_type: str) -> tuple[str, str, str]:
    return (run["detector"], json.dumps(run_params(run), sort_keys=True), sensor_type)


def pooled_budgets(
    results: Sequence[Mapping[str, Any]], target_per_hour: float
) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """The matched budget of each detector (with its parameters and false-alarm budget) on
    each sensor type, pooled over all its runs: false episodes and fault-free tested hours
    summed at every threshold scale (every run's channel of that type counts, faulty or
    not), matched to ``target_per_hour`` (:func:`~imufdi_cli.sweep.match_budget`), and
    each run's MAR, FIR and delays read at that scale.

    Returns the results with each run's ``*_at_budget`` figures filled in (copies; the
    run files are not changed: the match depends on every run of the campaign) and one
    entry per pool (its runs, false episodes and hours, the rate with its bounds, the
    threshold scale and why it could not be matched, if so)."""
    from imufdi_cli.metrics import budget_figures, episode_rate
    from imufdi_cli.sweep import BudgetCurve, match_budget

    curves: dict[tuple[str, str, str], list[tuple[int, str, BudgetCurve]]] = {}
    for index, result in enumerate(results):
        if not result.get("ok"):
            continue
        for sensor_type, figures in result["metrics"].items():
            data = figures.get("budget_curve")
            if data is None:
                continue
            key = _pool_key(result["run"], sensor_type)
            curves.setdefault(key, []).append((index, sensor_type, BudgetCurve.from_dict(data)))
    out = [dict(r) for r in results]
    pools = []
    for key, members in sorted(curves.items()):
        counts = np.sum([c.false_episodes for _, _, c in members], axis=0)
        hours = float(sum(c.hours for _, _, c in members))
        match = match_budget(counts, hours, target_per_hour)
        own = 0  # false episodes at each detector's own threshold
        own_hours = 0.0
        for index, sensor_type, curve in members:
            result = out[index]
            result["metrics"] = dict(result["metrics"])
            figures = dict(result["metrics"][sensor_type]) | budget_figures(curve, match)
            result["metrics"][sensor_type] = figures
            own += int(figures.get("false_episodes") or 0)
            own_hours += float(figures.get("fault_free_hours") or 0.0)
        detector, params, sensor_type = key
        pools.append(
            {
                "detector": detector,
                "params": json.loads(params),
                "sensor_type": sensor_type,
                "runs": len(members),
                "false_episodes": own,
                "fault_free_hours": own_hours,
                **episode_rate(own, own_hours),
                "target_budget_per_hour": target_per_hour,
                "threshold_scale_at_budget": match.scale,
                "note": match.note,
            }
        )
    return out, pools


def _pooled(rows: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """:data:`POOLED_METRICS` of a group: its runs' false episodes and fault-free tested
    hours summed, and the rate, bound and mean time between false alarms of the sums; each
    as ``{"mean": value, "std": None, "n": runs counted, "pooled": True}`` (the layout of
    the other figures, so that gates read it the same way)."""
    from imufdi_cli.metrics import episode_rate

    counted = [r for r in rows if r.get("false_episodes") is not None]
    count = int(sum(r["false_episodes"] for r in counted))
    hours = float(sum(r.get("fault_free_hours") or 0.0 for r in counted))
    values: dict[str, Any] = {"false_episodes": count if counted else None}
    values["fault_free_hours"] = hours if counted else None
    values |= episode_rate(count, hours) if counted else dict.fromkeys(POOLED_METRICS[2:])
    return {
        name: {"mean": values[name], "std": None, "n": len(counted), "pooled": True}
        for name in POOLED_METRICS
    }


def summarize(spec: CampaignSpec, results: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Means and spreads over seeds per base x detector x params x fault (spec without its
    amplitude, so faults on different sensors stay apart) x amplitude x sensor type,
    amplitudes in numeric order, plus detection probability against amplitude; the false
    alarm episodes pooled over each group's runs, and the figures at the budget matched
    over each detector's runs (:func:`pooled_budgets`)."""
    results, pools = pooled_budgets(results, spec.match_budget)
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
        for metric in dict.fromkeys([*spec.metrics, *BUDGET_METRICS]):
            if metric in POOLED_METRICS:
                continue
            mean, std, count = mean_metrics([r.get(metric) for r in rows])
            entry[metric] = {"mean": mean, "std": std, "n": count}
        entry |= _pooled(rows)
        targets = {float(r["target_far"]) for r in rows if r.get("target_far") is not None}
        if targets:
            entry["target_far"] = sorted(targets)[0]
        budgets = [
            float(r["target_budget_per_hour"]) for r in rows if r.get("target_budget_per_hour")
        ]
        if budgets:
            entry["target_budget_per_hour"] = min(budgets)
            scales = {r.get("threshold_scale_at_budget") for r in rows}
            entry["threshold_scale_at_budget"] = scales.pop() if len(scales) == 1 else None
        table.append(entry)
    failures = [{"key": r["key"], "error": r.get("error", "")} for r in results if not r["ok"]]
    return {
        "name": spec.name,
        "spec": spec.source,
        "runs": len(results),
        "failed": len(failures),
        "metrics": spec.metrics,
        "groups": table,
        "budgets": pools,
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
        "mar_at_budget",
        "fir_at_budget",
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
    if summary.get("budgets"):
        lines += ["", *_budget_tables(summary)]
    curves = summary.get("curves") or []
    if curves:
        lines += ["", "## Detection probability against amplitude", "", *_curves_table(curves)]
    if summary["failures"]:
        lines += ["", "## Failed runs", ""]
        lines += [f"- `{f['key']}`: {f['error']}" for f in summary["failures"]]
    return "\n".join(lines) + "\n"


def _number(value: float | None, scale: float = 1.0, fmt: str = "{:.3g}") -> str:
    return "undefined" if value is None else fmt.format(value * scale)


def _budget_tables(summary: Mapping[str, Any]) -> list[str]:
    """The false-alarm budget: per detector and type, the false alarm episodes pooled over
    all its runs and the threshold scale matching the target; per group, the pooled rate
    and the figures at that scale (mean ± std over seeds), with the reference delays."""
    pools = summary["budgets"]
    target = pools[0]["target_budget_per_hour"]
    lines = [
        "## False alarm budget",
        "",
        "False alarm episodes (the episodes' joining rule) starting on fault-free samples"
        " outside the calibration window, per hour of fault-free tested time, pooled over"
        " runs, with the exact Poisson 95 % upper bound; `*_at_budget` with each"
        f" detector's threshold scaled so that its runs pooled raise {target:g} false"
        " episodes per hour (docs/metrics.md).",
        "",
        "| detector | params | type | runs | false episodes | hours | per hour | upper 95 %"
        " | MTBFA h (lower 95 %) | scale at budget |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for p in pools:
        scale = _number(p["threshold_scale_at_budget"]) if p["note"] is None else p["note"]
        lines.append(
            f"| {p['detector']} | {_params_text(p['params'])} | {p['sensor_type']} | {p['runs']}"
            f" | {p['false_episodes']} | {p['fault_free_hours']:.3g}"
            f" | {_number(p['false_episodes_per_hour'])}"
            f" | {_number(p['false_episodes_per_hour_upper95'])}"
            f" | {_number(p['mtbfa_h'])} ({_number(p['mtbfa_h_lower95'])}) | {scale} |"
        )
    lines += [
        "",
        "| base | detector | params | fault | amplitude | type | false / h [upper 95 %]"
        " | hours | MAR@budget % | FIR@budget % | delay@budget s | iso delay@budget s"
        " | reference delay s | delay / reference |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for g in summary["groups"]:
        rate = g["false_episodes_per_hour"]["mean"]
        upper = g["false_episodes_per_hour_upper95"]["mean"]
        cells = [
            g["base"],
            g["detector"],
            _params_text(g["params"]),
            g.get("fault", g["model"]),
            g["amplitude"],
            g["sensor_type"],
            f"{_number(rate)} [{_number(upper)}]",
            _number(g["fault_free_hours"]["mean"]),
        ]
        for name in BUDGET_METRICS:
            cells.append(_stat_text(g[name], 100.0 if name in PERCENT_METRICS else 1.0))
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def _stat_text(stat: Mapping[str, Any], scale: float) -> str:
    if stat["mean"] is None:
        return "undefined"
    if stat["std"] is None:
        return f"{stat['mean'] * scale:.3g}"
    return f"{stat['mean'] * scale:.3g} ± {stat['std'] * scale:.2g}"


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
