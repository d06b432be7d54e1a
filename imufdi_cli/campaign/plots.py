"""The campaign figure: detection probability against fault amplitude.

``detection_probability.png`` has one panel per base x fault (spec without its amplitude)
x scored sensor type. Each detector configuration is one colour in every panel (the
detector's colour, :data:`imufdi_cli.colours.DETECTOR_COLOURS`, in shades for its parameter sets) and one
marker; its per-event detection probability is a solid line, the per-sample detection
rate 1 - MAR a dashed one. Curves that coincide (several detectors at 100 %) stay visible:
each configuration is shifted sideways by a small fixed step and drawn with its own
marker, larger markers behind smaller ones. Amplitudes are on the spec's units (``deg/s``
is drawn as °/s), detection figures in %. One legend for the whole figure, with the
parameters as ``pca-parity α=0.001`` (no JSON).
"""

from __future__ import annotations

import json
import math
from collections import Counter
from collections.abc import Mapping, Sequence
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


def plot_curves(summary: Mapping[str, Any], out: Path) -> None:
    """Write ``detection_probability.png`` in ``out`` (needs matplotlib: the plot extra).

    Raises
    ------
    UsageError
        matplotlib is not installed.
    """
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        from matplotlib.lines import Line2D
    except ImportError as err:
        raise UsageError("plots need matplotlib") from err
    rates = _detection_rates(summary)
    panels: dict[tuple[str, str, str], list[dict[str, Any]]] = {}
    for c in summary.get("curves", []):
        panels.setdefault((c["base"], c.get("fault", c["model"]), c["sensor_type"]), []).append(c)
    if not panels:
        return
    styles = _styles(summary.get("curves", []))
    columns = min(2, len(panels))
    rows = math.ceil(len(panels) / columns)
    fig, axes = plt.subplots(
        rows,
        columns,
        figsize=(6.2 * columns, 3.9 * rows + 0.9),
        squeeze=False,
        constrained_layout=True,
    )
    for ax, ((base, fault, sensor_type), curves) in zip(axes.flat, sorted(panels.items())):
        _panel(ax, base, fault, sensor_type, curves, styles, rates)
    for ax in list(axes.flat)[len(panels) :]:
        ax.set_visible(False)
    handles = [
        Line2D([], [], color=s["color"], marker=s["marker"], markersize=s["size"], label=label)
        for label, s in styles.items()
    ]
    handles += [
        Line2D([], [], color="0.3", linestyle="-", label="detection probability (per fault)"),
        Line2D([], [], color="0.3", linestyle="--", label="1 − MAR (per sample)"),
    ]
    fig.legend(
        handles=handles,
        loc="outside lower center",
        ncols=min(4, len(handles)),
        fontsize=9,
        frameon=False,
    )
    fig.suptitle(f"Campaign {summary.get('name', '')}: detection against fault amplitude")
    from imufdi_cli.plots import save_figure  # the layout once, not a draw for it

    try:
        with atomic_path(out / "detection_probability.png", suffix=".png") as tmp:
            save_figure(fig, tmp, 100)  # matplotlib takes the format from the extension
    finally:
        plt.close(fig)


def _detection_rates(summary: Mapping[str, Any]) -> dict[tuple[str, ...], float]:
    """1 - mean MAR per base, detector, params, fault and amplitude (when aggregated)."""
    rates: dict[tuple[str, ...], float] = {}
    for g in summary["groups"]:
        mar = g.get("mar")
        if mar is not None and mar["mean"] is not None:
            params = json.dumps(g["params"], sort_keys=True)
            key = (g["base"], g["detector"], params, g.get("fault", g["model"]), g["amplitude"])
            rates[key] = 1.0 - mar["mean"]
    return rates


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
    base: str,
    fault: str,
    sensor_type: str,
    curves: Sequence[Mapping[str, Any]],
    styles: Mapping[str, Mapping[str, Any]],
    rates: Mapping[tuple[str, ...], float],
) -> None:
    unit, xs = panel_axis(curves)
    known = [x for values in xs.values() for x in values if x is not None]
    span = (max(known) - min(known)) if len(known) > 1 else 1.0
    span = span or 1.0
    for index, c in enumerate(curves):
        style = styles[detector_label(c["detector"], c["params"])]
        shift = DODGE * span * (style["rank"] - (style["of"] - 1) / 2.0)
        params = json.dumps(c["params"], sort_keys=True)
        points = [(x, p) for x, p in zip(xs[index], c["points"]) if x is not None]
        x = np.array([v + shift for v, _ in points], dtype=float)
        probability = [np.nan if p["mean"] is None else 100.0 * p["mean"] for _, p in points]
        rate = [
            100.0 * rates.get((base, c["detector"], params, fault, p["amplitude"]), np.nan)
            for _, p in points
        ]
        common = {
            "color": style["color"],
            "marker": style["marker"],
            "markersize": style["size"],
            "zorder": 3 + style["rank"],  # later (smaller) markers on top
        }
        ax.plot(x, probability, linestyle="-", linewidth=1.6, **common)
        ax.plot(
            x,
            rate,
            linestyle="--",
            linewidth=1.2,
            markerfacecolor="white",
            alpha=0.85,
            **common,
        )
    ticks = sorted(set(round(v, 12) for v in known))
    if 0 < len(ticks) <= 8:
        ax.set_xticks(ticks, [f"{t:g}" for t in ticks])
    model = curves[0].get("model", fault.split(":", 1)[0])
    ax.set_xlabel(_x_label(model, unit))
    ax.set_ylabel("detected, %")
    ax.set_ylim(-3, 104)
    ax.set_title(f"{base}\n{fault} · scored on {sensor_type}", fontsize=9)
    ax.grid(alpha=0.3)
