"""The episode targets (docs/episodes.md) per fault model, pooled over presets and detectors, from episode dumps.

Usage::

    python studies/episodes_pooled.py c6a.json c6b.json p4a.json p4b.json w12a.json ...

Reads ``episodes.py --dump`` files (any presets, disjoint seeds per preset) and
prints, for each fault model of the reference set:

- class right: the share of the matched episodes whose class is the true model
  (target >= 90 % per model);
- coverage: the share of the sized episodes whose 90 % interval covers the injected size
  (target 85-95 %), with its Clopper-Pearson 95 % interval;

first pooled over every preset and detector (the targets' "per model"), then per preset and
per detector, then per (preset, detector, model) cell. For the cells it also prints how
many lie outside the 85-95 % band and how many a calibrated 90 % interval would leave out
by chance with the same cell sizes (exact binomial sums, cells taken as independent), so a
reader can tell miscalibration from the spread of small cells.
"""

from __future__ import annotations

import argparse
import json
import os
from collections import defaultdict
from pathlib import Path
from typing import Any

from episodes import clopper_pearson
from scipy.stats import binom

BAND = (0.85, 0.95)


def _tally(rows: list[dict[str, Any]]) -> tuple[int, int, int, int]:
    """(episodes, class right, sized, covered) of matched episode records."""
    right = sum(bool(r["class_right"]) for r in rows)
    sized = [r for r in rows if r["covered"] is not None]
    return len(rows), right, len(sized), sum(bool(r["covered"]) for r in sized)


def _line(label: str, rows: list[dict[str, Any]]) -> str:
    n, right, n_sized, covered = _tally(rows)
    klass = f"{100 * right / n:.1f} % ({right}/{n})" if n else "-"
    if n_sized:
        lo, hi = clopper_pearson(covered, n_sized)
        share = covered / n_sized
        ok = "in band" if BAND[0] <= share <= BAND[1] else "OUT"
        cov = f"{100 * share:.1f} % ({covered}/{n_sized}) | {100 * lo:.1f}-{100 * hi:.1f} % | {ok}"
    else:
        cov = "- | - | -"
    return f"| {label} | {klass} | {cov} |"


def _p_out_of_band(n: int, p: float = 0.9) -> float:
    """Probability that a calibrated interval's coverage in n episodes leaves the band."""
    k_lo = int(-(-BAND[0] * n // 1))  # smallest k with k/n >= 0.85
    k_hi = int(BAND[1] * n // 1)  # largest k with k/n <= 0.95
    return float(1.0 - (binom.cdf(k_hi, n, p) - binom.cdf(k_lo - 1, n, p)))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("dumps", nargs="+", help="episodes.py --dump files")
    args = parser.parse_args()
    # (preset, detector, model) -> matched episode records
    cells: dict[tuple[str, str, str], list[dict[str, Any]]] = defaultdict(list)
    seeds: dict[str, list[str]] = defaultdict(list)
    for path in args.dumps:
        state = json.loads(Path(path).read_text())
        preset = state["preset"]
        seeds[preset] += [f"{a}-{b - 1}" for a, b in state["seeds"]]
        for key, rows in state["rows"].items():
            detector, model = key.split("|")
            cells[(preset, detector, model)] += rows
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    print("seeds: " + "; ".join(f"{p} {', '.join(s)}" for p, s in sorted(seeds.items())))
    print(f"load average {load}")
    models = sorted({m for _, _, m in cells}, key=lambda m: list(_ORDER).index(m))
    header = (
        "| {} | class right | 90 % interval covers | coverage 95 % CI | 85-95 % band |\n"
        "|---|---|---|---|---|"
    )
    print("\nPer model, pooled over presets and detectors:\n")
    print(header.format("fault"))
    for model in models:
        print(_line(model, [r for (_, _, m), v in cells.items() if m == model for r in v]))
    for axis, name in ((0, "preset"), (1, "detector")):
        print(f"\nPer model and {name}:\n")
        print(header.format(f"fault, {name}"))
        for model in models:
            for value in sorted({k[axis] for k in cells if k[2] == model}):
                rows = [
                    r for k, v in cells.items() if k[2] == model and k[axis] == value for r in v
                ]
                print(_line(f"{model}, {value}", rows))
    sized_cells = {
        k: _tally(v) for k, v in cells.items() if _tally(v)[2] > 0 and k[1] != "variance-drop"
    }
    out = [k for k, (_, _, n, c) in sized_cells.items() if not BAND[0] <= c / n <= BAND[1]]
    expected = sum(_p_out_of_band(n) for _, _, n, _ in sized_cells.values())
    print(
        f"\nCells (preset, detector, model) with sized episodes: {len(sized_cells)};"
        f" outside the 85-95 % band: {len(out)}; a calibrated 90 % interval would leave"
        f" {expected:.1f} out on average with these cell sizes."
    )
    for k in sorted(out):
        _, _, n, c = sized_cells[k]
        print(f"  {' / '.join(k)}: {100 * c / n:.1f} % ({c}/{n})")
    return 0


_ORDER = ("step", "drift", "noise", "stuck", "spikes", "scale")

if __name__ == "__main__":
    raise SystemExit(main())
