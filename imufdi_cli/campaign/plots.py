"""The campaign figure: missed-alarm rate and detection delay at a matched false-alarm
level, against fault amplitude.

``detection.png`` has one row per base x fault (spec without its amplitude) x scored
sensor type, and two panels in it: **MAR** (the per-sample missed-alarm rate; detection
rate = 1 - MAR, the papers' definition) and the mean **detection delay** at decision time,
both with every detector at the same false-alarm level, so that a detector cannot look
better by alarming more. The level is the false-alarm budget (``mar_at_budget``,
``detection_delay_s_at_budget`` at ``target_budget_per_hour``) when the summary has it, else
the matched FAR (``mar_at_far``, ``detection_delay_at_far_s`` at ``target_far``):
:func:`headline_metrics` chooses. Each detector configuration is one colour in every panel
(the detector's colour, :data:`imufdi_cli.colours.DETECTOR_COLOURS`, in shades for its
parameter sets) and one marker; configurations that coincide stay visible (shifted
sideways by a small fixed step, larger markers behind smaller ones). Amplitudes are on the
spec's units (``deg/s`` is drawn as °/s). One legend for the whole figure, below the
panels and inside the canvas (as many columns as fit its width), with the parameters as
``pca-parity α=0.001`` (no JSON).
"""

from __future__ import annotations

import json
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from imufdi_cli.colours import detector_colour as base_colour
from imufdi_cli.errors import ImufdiError, UsageError
from imufdi_cli.fileio import atomic_path

#: Markers of the configurations, in legend order (large ones first: drawn behind).
MARKERS = ("o", "s", "D", "^", "v", "P", "X", "<", ">", "*")
MARKER_SIZES = (9.0, 7.5, 6.5, 6.5, 6.5, 6.5, 6.0, 6.0, 6.0, 7.0)
#: Sideways shift between configurations, as a fraction of the panel's amplitude span.
DODGE = 0.012
#: Parameter names written as symbols in legends.
SYMBOLS = {"alpha": "α", "beta": "β", "lambda": "λ", "sigma": "σ", "gamma": "γ"}
#: What the amplitude of a fault model is, for the x label.
AMPLITUDE_NAMES = {
    "step": "step amplitude",
    "drift": "drift rate",
    "noise": "noise factor",
    "scale": "scale factor",
    "spikes": "spike amplitude",
}


def detector_label(detector: str, params: Mapping[str, Any]) -> str:
    """``pca-parity α=0.001``, ``glt window=10``, ``glt`` (default parameters)."""
    items = [f"{SYMBOLS.get(k, k)}={_number(v)}" for k, v in sorted(params.items())]
    return " ".join([detector, *items])


def _number(value: Any) -> str:
    return f"{value:g}" if isinstance(value, float) else str(value)


def detector_colour(detector: str, variant: int = 0, variants: int = 1) -> str:
    """The detector's colour; parameter set ``variant`` of ``variants`` in a shade of it
    (the first, usually the defaults, in the colour itself, the others darker)."""
    base = base_colour(detector)
    if variant == 0 or variants <= 1:
        return base
    import matplotlib.colors as mcolors  # only for the shades

    shade = 1.0 - 0.45 * variant / (variants - 1 if variants > 2 else 1)
    r, g, b = (min(1.0, max(0.0, c * shade)) for c in mcolors.to_rgb(base))
    return str(mcolors.to_hex((r, g, b)))


def pretty_unit(unit: str) -> str:
    """A spec unit for an axis label: ``deg/s`` -> ``°/s``, ``deg/s^2`` -> ``°/s²``."""
    text = unit.replace("deg", "°").replace("^2", "²").replace("^3", "³").replace("^-1", "⁻¹")
    return text.replace("*", "·")


def _unit_scale(unit: str, sensor_type: str) -> float | None:
    """SI value of one ``unit`` for the sensor type (amplitude, then rate dimension)."""
    from imufdi_cli.units import parse_quantity, rate_dimension, sensor_dimension

    for dimension in (sensor_dimension, rate_dimension):
        try:
            return float(parse_quantity(f"1{unit}", dimension(sensor_type)))
        except (ImufdiError, ValueError, KeyError):
            continue
    return None


def panel_axis(curves: Sequence[Mapping[str, Any]]) -> tuple[str, dict[int, list[float | None]]]:
    """The x unit of a panel (the unit most of its points are written in) and each curve's
    x values in it: points written in another unit are converted through SI, so a panel
    never falls back to SI (rad/s) when the spec writes deg/s."""
    units = Counter(p.get("amplitude_unit") or "" for c in curves for p in c["points"])
    unit = units.most_common(1)[0][0] if units else ""
    xs: dict[int, list[float | None]] = {}
    for index, c in enumerate(curves):
        scale = _unit_scale(unit, c["sensor_type"]) if unit else None
        values: list[float | None] = []
        for p in c["points"]:
            if (p.get("amplitude_unit") or "") == unit:
                values.append(p.get("amplitude_value"))
            elif scale and p.get("amplitude_si") is not None:
                values.append(p["amplitude_si"] / scale)
            else:
                values.append(None)
        xs[index] = values
    return unit, xs


def _x_label(model: str, unit: str) -> str:
    name = AMPLITUDE_NAMES.get(model, f"{model} amplitude")
    if not unit:
        return f"{name} (× nominal)" if model in ("noise", "scale") else name
    return f"{name}, {pretty_unit(unit)}"


#: file name of the campaign figure in the results directory
FIGURE = "detection.png"


@dataclass(frozen=True)
class Headline:
    """What the campaign figure plots: the MAR and delay metrics and their level."""

    mar: str
    delay: str
    level: str  # e.g. "matched FAR 1 %", "a budget of 1 false episode/h"


def headline_metrics(summary: Mapping[str, Any]) -> Headline:
    """The budget metrics (``mar_at_budget``, ``detection_delay_s_at_budget``) when the
    summary's groups have them defined (a matched budget), else the matched-FAR ones (``mar_at_far``,
    ``detection_delay_at_far_s``)."""
    groups = summary.get("groups") or []
    matched = (g.get("mar_at_budget") for g in groups)
    if any(isinstance(m, Mapping) and m.get("mean") is not None for m in matched):
        budgets = sorted(
            {float(g["target_budget_per_hour"]) for g in groups if g.get("target_budget_per_hour")}
        )
        level = (
            f"a budget of {budgets[0]:g} false episodes/h" if budgets else "the false-alarm budget"
        )
        return Headline("mar_at_budget", "detection_delay_s_at_budget", level)
    targets = sorted({float(g["target_far"]) for g in groups if g.get("target_far") is not None})
    level = f"matched FAR {100 * targets[0]:g} %" if targets else "matched FAR"
    return Headline("mar_at_far", "detection_delay_at_far_s", level)


def headline_curves(
    summary: Mapping[str, Any], metric: str
) -> dict[tuple[str, str, str], list[dict[str, Any]]]:
    """Curves of one metric against amplitude, per panel (base, fault, sensor type): one
    curve per detector configuration, points in SI amplitude order with the spec's own
    amplitude value and unit (as :func:`~imufdi_cli.campaign.summary.detection_curves`)."""
    from imufdi_cli.campaign.summary import _amplitude_number, _amplitude_si

    curves: dict[tuple[str, ...], dict[str, Any]] = {}
    for g in summary.get("groups") or []:
        stat = g.get(metric)
        if not isinstance(stat, Mapping):
            continue
        fault = g.get("fault", g["model"])
        params = json.dumps(g["params"], sort_keys=True)
        key = (g["base"], fault, g["sensor_type"], g["detector"], params)
        curve = curves.setdefault(
            key,
            {
                "base": g["base"],
                "fault": fault,
                "model": g["model"],
                "sensor_type": g["sensor_type"],
                "detector": g["detector"],
                "params": g["params"],
                "points": [],
            },
        )
        value, unit = _amplitude_number(g["amplitude"])
        curve["points"].append(
            {
                "amplitude": g["amplitude"],
                "amplitude_si": _amplitude_si(g["amplitude"], g["sensor_type"]),
                "amplitude_value": value,
                "amplitude_unit": unit,
                "mean": stat.get("mean"),
                "std": stat.get("std"),
                "n": stat.get("n"),
            }
        )
    panels: dict[tuple[str, str, str], list[dict[str, Any]]] = {}
    for where, curve in sorted(curves.items()):
        curve["points"].sort(key=lambda p: (p["amplitude_si"] is None, p["amplitude_si"] or 0.0))
        panels.setdefault((where[0], where[1], where[2]), []).append(curve)
    return panels


def plot_curves(summary: Mapping[str, Any], out: Path) -> None:
    """Write :data:`FIGURE` in ``out`` (needs matplotlib: the plot extra); nothing when the
    summary has neither headline metric (a campaign without ``mar_at_far``).

    Raises
    ------
    UsageError
        matplotlib is not installed.
    """
    fig = figure_curves(summary)
    if fig is None:
        return
    import matplotlib.pyplot as plt

    from imufdi_cli.plots import save_figure  # the layout once, not a draw for it

    try:
        with atomic_path(out / FIGURE, suffix=".png") as tmp:
            save_figure(fig, tmp, 100)  # matplotlib takes the format from the extension
    finally:
        plt.close(fig)


def figure_curves(summary: Mapping[str, Any]) -> Any:
    """The campaign figure (a matplotlib Figure, laid out, not saved), or None when there
    is nothing to draw."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        from matplotlib.lines import Line2D
    except ImportError as err:
        raise UsageError("plots need matplotlib") from err
    headline = headline_metrics(summary)
    mar = headline_curves(summary, headline.mar)
    if not mar:
        return None
    delay = headline_curves(summary, headline.delay)
    styles = _styles([c for curves in mar.values() for c in curves])
    rows = len(mar)
    fig, axes = plt.subplots(
        rows, 2, figsize=(12.4, 3.6 * rows + 1.3), squeeze=False, constrained_layout=True
    )
    for (ax_mar, ax_delay), (key, curves) in zip(axes, sorted(mar.items())):
        base, fault, sensor_type = key
        _panel(ax_mar, curves, styles, percent=True)
        ax_mar.set_ylabel("MAR, % of faulty samples")
        ax_mar.set_ylim(-3, 104)
        ax_mar.set_title(f"{base}\n{fault} · scored on {sensor_type}: MAR", fontsize=9)
        if key in delay:
            _panel(ax_delay, delay[key], styles, percent=False)
            ax_delay.set_ylabel("detection delay, s (decision time)")
            ax_delay.set_title(
                f"{base}\n{fault} · scored on {sensor_type}: detection delay", fontsize=9
            )
        else:
            ax_delay.text(
                0.5,
                0.5,
                f"no {headline.delay} in this campaign's metrics",
                ha="center",
                va="center",
                transform=ax_delay.transAxes,
                fontsize=9,
            )
            ax_delay.set_xticks([])
            ax_delay.set_yticks([])
    handles = [
        Line2D([], [], color=s["color"], marker=s["marker"], markersize=s["size"], label=label)
        for label, s in styles.items()
    ]
    fig.suptitle(
        f"Campaign {summary.get('name', '')}: missed alarms and detection delay at"
        f" {headline.level}, against fault amplitude"
    )
    _legend_inside(fig, handles)
    return fig


def _legend_inside(fig: Any, handles: list[Any]) -> Any:
    """One legend below the panels with as many columns as fit the figure's width (the
    text measured by the renderer), so that it is never cut off at the sides."""
    renderer = fig.canvas.get_renderer()
    width = fig.get_window_extent(renderer).width
    for ncols in range(min(5, len(handles)), 0, -1):
        legend = fig.legend(
            handles=handles, loc="outside lower center", ncols=ncols, fontsize=9, frameon=False
        )
        if legend.get_window_extent(renderer).width <= 0.96 * width or ncols == 1:
            return legend
        legend.remove()
    return None


def _styles(curves: Sequence[Mapping[str, Any]]) -> dict[str, dict[str, Any]]:
    """Colour, marker and sideways rank of every detector configuration of the figure,
    the same in every panel (legend order: detector name, default parameters first)."""
    configs = sorted(
        {(c["detector"], json.dumps(c["params"], sort_keys=True)) for c in curves},
        key=lambda item: (item[0], item[1] != "{}", item[1]),  # defaults first
    )
    per_detector: dict[str, list[str]] = {}
    for detector, params in configs:
        per_detector.setdefault(detector, []).append(params)
    styles: dict[str, dict[str, Any]] = {}
    for rank, (detector, params) in enumerate(configs):
        variants = per_detector[detector]
        label = detector_label(detector, json.loads(params))
        styles[label] = {
            "color": detector_colour(detector, variants.index(params), len(variants)),
            "marker": MARKERS[rank % len(MARKERS)],
            "size": MARKER_SIZES[rank % len(MARKER_SIZES)],
            "rank": rank,
            "of": len(configs),
        }
    return styles


def _panel(
    ax: Any,
    curves: Sequence[Mapping[str, Any]],
    styles: Mapping[str, Mapping[str, Any]],
    *,
    percent: bool,
) -> None:
    """One metric of every configuration against amplitude, on the spec's units."""
    unit, xs = panel_axis(curves)
    known = [x for values in xs.values() for x in values if x is not None]
    span = (max(known) - min(known)) if len(known) > 1 else 1.0
    span = span or 1.0
    drawn: list[float] = []
    for index, c in enumerate(curves):
        style = styles[detector_label(c["detector"], c["params"])]
        shift = DODGE * span * (style["rank"] - (style["of"] - 1) / 2.0)
        points = [(x, p) for x, p in zip(xs[index], c["points"]) if x is not None]
        x = np.array([v + shift for v, _ in points], dtype=float)
        scale = 100.0 if percent else 1.0
        y = np.array([np.nan if p["mean"] is None else scale * float(p["mean"]) for _, p in points])
        drawn.extend(y[np.isfinite(y)].tolist())
        ax.plot(
            x,
            y,
            linestyle="-",
            linewidth=1.5,
            color=style["color"],
            marker=style["marker"],
            markersize=style["size"],
            zorder=3 + style["rank"],  # later (smaller) markers on top
        )
    ticks = sorted(set(round(v, 12) for v in known))
    if 0 < len(ticks) <= 8:
        ax.set_xticks(ticks, [f"{t:g}" for t in ticks])
    model = curves[0].get("model", str(curves[0].get("fault", "")).split(":", 1)[0])
    ax.set_xlabel(_x_label(model, unit))
    positive = [v for v in drawn if v > 0]
    if not percent and positive and max(positive) / min(positive) > 30:
        ax.set_yscale("log")  # delays from milliseconds to seconds
    ax.grid(alpha=0.3, which="both")
