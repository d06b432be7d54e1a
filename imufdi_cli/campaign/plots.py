"""The campaign figure: detection probability against fault amplitude."""

from __future__ import annotations

import json
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from imufdi_cli.errors import UsageError
from imufdi_cli.fileio import atomic_path

if sys.version_info >= (3, 11):
    pass
else:  # pragma: no cover
    pass


def plot_curves(summary: Mapping[str, Any], out: Path) -> None:
    """``detection_probability.png``: one panel per base x fault model x sensor type, with
    the per-event detection probability (solid) and, when MAR is aggregated, the per-sample
    detection rate 1 - MAR (dashed) of each detector against the SI amplitude (plot extra).
    """
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as err:
        raise UsageError("plots need matplotlib") from err
    rates: dict[tuple[str, str, str, str, str], float] = {}
    for g in summary["groups"]:
        mar = g.get("mar")
        if mar is not None and mar["mean"] is not None:
            params = json.dumps(g["params"], sort_keys=True)
            key = (g["base"], g["detector"], params, g.get("fault", g["model"]), g["amplitude"])
            rates[key] = 1.0 - mar["mean"]
    panels: dict[tuple[str, str, str], list[dict[str, Any]]] = {}
    for c in summary.get("curves", []):
        panels.setdefault((c["base"], c.get("fault", c["model"]), c["sensor_type"]), []).append(c)
    if not panels:
        return
    fig, axes = plt.subplots(
        1, len(panels), figsize=(4.2 * len(panels), 3.8), squeeze=False, constrained_layout=True
    )
    for ax, ((base, model, sensor_type), curves) in zip(axes[0], sorted(panels.items())):
        for index, c in enumerate(curves):
            params = json.dumps(c["params"], sort_keys=True)
            label = c["detector"] + ("" if not c["params"] else " " + params)
            unit = c.get("unit")
            field = "amplitude_value" if unit is not None else "amplitude_si"
            points = [p for p in c["points"] if p.get(field) is not None]
            xs = [p[field] for p in points]
            color = f"C{index % 10}"
            probability = [np.nan if p["mean"] is None else p["mean"] for p in points]
            ax.plot(xs, probability, "o-", color=color, label=label)
            rate = [
                rates.get((base, c["detector"], params, model, p["amplitude"]), np.nan)
                for p in points
            ]
            ax.plot(xs, rate, "s--", color=color, alpha=0.7)
        ax.set_title(f"{base} · {model} · {sensor_type}", fontsize=9)
        units = {c.get("unit") for c in curves}
        unit = units.pop() if len(units) == 1 else None
        if unit is None:
            ax.set_xlabel("fault amplitude (SI)")
        else:
            ax.set_xlabel(f"fault amplitude, {unit}" if unit else "fault amplitude")
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    axes[0][0].set_ylabel("detection probability (solid), 1 - MAR (dashed)")
    try:
        with atomic_path(out / "detection_probability.png", suffix=".png") as tmp:
            fig.savefig(tmp, dpi=100)  # matplotlib takes the format from the extension
    finally:
        plt.close(fig)
