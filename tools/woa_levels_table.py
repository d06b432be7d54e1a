"""The levels table of docs/algorithms/woa-mvmd-glt.md from a woa-mvmd-glt-levels campaign.

Run:
    imufdi campaign docs/campaigns/woa-mvmd-glt-levels.toml -o results/woa-levels --jobs 1
    python tools/woa_levels_table.py results/woa-levels/runs.csv [--alpha 0.01]

Per sensor type: the fault-free FAR (runs whose fault is on the other type: this type is
fault-free for the whole log; FAR after the calibration window, mean and worst seed, and
how many seeds exceed 4 alpha), and from the runs with a fault on this type the FAR before
the onset, MAR, FIR, detection delay at decision time (mean and worst) and the mean decision
latency. Targets (every detector holds its nominal false-alarm level):
fault-free FAR <= 1.5 alpha (no seed above 4 alpha) and, for the gyro step, MAR <= 1.5 %.
"""

from __future__ import annotations

import argparse
import csv
import statistics
from collections import defaultdict


def _float(value: str) -> float:
    return float(value) if value not in ("", None) else float("nan")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("runs", help="runs.csv of the campaign")
    parser.add_argument("--alpha", type=float, default=0.01, help="the detector's alpha")
    args = parser.parse_args()
    alpha = args.alpha
    free: dict[str, list[float]] = defaultdict(list)
    faulty: dict[tuple[str, str], list[dict[str, str]]] = defaultdict(list)
    seeds = set()
    with open(args.runs, newline="", encoding="utf-8") as handle:
        for row in csv.DictReader(handle):
            if row["ok"] != "True" or not row["sensor_type"]:
                continue
            seeds.add(row["seed"])
            fault_type = row["sensor"].split(".")[1]
            if fault_type == row["sensor_type"]:
                faulty[(row["sensor_type"], f"{row['fault']} {row['amplitude']}")].append(row)
            else:
                free[row["sensor_type"]].append(_float(row["far"]))
    print(f"seeds {min(seeds)}-{max(seeds)} ({len(seeds)}), alpha = {100 * alpha:g} %")
    print()
    print("| type | fault-free FAR % (mean, worst seed; seeds > 4 alpha) | target |")
    print("|---|---|---|")
    for sensor_type, fars in sorted(free.items()):
        mean, worst = statistics.mean(fars), max(fars)
        over = sum(f > 4 * alpha for f in fars)
        met = mean <= 1.5 * alpha and over == 0
        print(
            f"| {sensor_type} | {100 * mean:.2f} ({100 * worst:.2f}; {over} of {len(fars)}) |"
            f" <= {150 * alpha:g} %, none > {400 * alpha:g} %: {'met' if met else 'NOT met'} |"
        )
    print()
    print(
        "| type | fault | runs | FAR before onset % | MAR % | FIR % | detection delay s"
        " (mean, worst) | decision latency s |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for (sensor_type, fault), rows in sorted(faulty.items()):

        def mean(name: str, rows: list[dict[str, str]] = rows) -> float:
            values = [_float(r[name]) for r in rows]
            return (
                statistics.mean(v for v in values if v == v)
                if any(v == v for v in values)
                else float("nan")
            )

        delays = [_float(r["detection_delay_s"]) for r in rows]
        print(
            f"| {sensor_type} | {fault} | {len(rows)} | {100 * mean('far'):.2f} |"
            f" {100 * mean('mar'):.2f} | {100 * mean('fir'):.2f} |"
            f" {mean('detection_delay_s'):.3f} ({max(delays):.3f}) |"
            f" {mean('decision_latency_s'):.3f} |"
        )


if __name__ == "__main__":
    main()
