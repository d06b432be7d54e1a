"""Each simultaneous fault's amplitude, through the tool: ``imufdi simulate``, ``inject``,
``detect -d bank``, then ``imufdi report --json`` (bank's target: every
simultaneous fault gets its amplitude within 5 %, measured from the written file).

Two scenarios, per seed:

- ``marg``: quadrotor-marg, a 0.5 rad/s step on imu0.gyro.z and a 0.1 rad/s^2 drift on
  imu0.gyro.x, both from 5 s (the bank's marg mode: filtered gyro residuals);
- ``array``: paper-table4, 0.9 deg/s steps on imu0.gyro.x and imu5.gyro.y from 2.5 s (the
  bank's array mode: leave-one-out residuals with exclusion).

Calibration 0-2 s. The figure is the report's per-fault ``amplitudes[].ratio``: estimated
size / injected size (a step's median amplitude where its sensor is isolated, a drift's
slope). Prints one row per seed, then mean, worst and the count within 5 %, and the load.

Usage: python studies/bank_amplitudes.py [--seeds 13000:13020] [--scenario marg,array]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

SCENARIOS = {
    "marg": (
        "quadrotor-marg",
        ["step:imu0.gyro.z,at=5s,amp=0.5rad/s", "drift:imu0.gyro.x,at=5s,rate=0.1rad/s^2"],
    ),
    "array": (
        "paper-table4",
        ["step:imu0.gyro.x,at=2.5s,amp=0.9deg/s", "step:imu5.gyro.y,at=2.5s,amp=0.9deg/s"],
    ),
}


def imufdi(*args: object) -> None:
    """Run the real command line (a fresh process, as a user would)."""
    command = [sys.executable, "-m", "imufdi_cli", str(args[0]), "-q", *map(str, args[1:])]
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(command)}: exit {done.returncode}: {done.stderr.strip()}")


def one_run(scenario: str, seed: int, work: Path) -> dict[str, dict[str, float]]:
    """Per fault id: ratio (estimate / true), sensor, and the share of its detected
    samples isolated to it."""
    preset_name, specs = SCENARIOS[scenario]
    clean, faulty, detected, report = (work / n for n in ("s.mcap", "f.mcap", "d.mcap", "r.json"))
    imufdi("simulate", "--preset", preset_name, "--seed", seed, "-o", clean)
    faults = [item for spec in specs for item in ("--fault", spec)]
    imufdi("inject", clean, *faults, "--seed", seed, "-o", faulty)
    imufdi("detect", faulty, "-d", "bank", "--calibrate", "0s:2s", "-o", detected)
    imufdi("report", detected, "--json", report)
    data = json.loads(report.read_text())
    gyro = next(r for r in data["results"] if r["sensor_type"] == "gyro")
    out = {}
    for fault in gyro["faults"]:
        amplitudes = fault["amplitudes"]
        out[fault["fault_id"]] = {
            "ratio": amplitudes[0]["ratio"] if amplitudes else float("nan"),
            "isolated": fault["isolated_correctly"],
            "sensors": len(amplitudes),
        }
    out["_mar"] = {"ratio": gyro["mar"]}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="13000:13020", help="START:STOP")
    parser.add_argument("--scenario", default="marg,array")
    args = parser.parse_args()
    start, stop = (int(v) for v in args.seeds.split(":"))
    for scenario in args.scenario.split(","):
        print(f"\n## {scenario}: {' + '.join(SCENARIOS[scenario][1])}, seeds {start}-{stop - 1}")
        print(
            "| seed | gyro MAR | f0 estimate / true | f1 estimate / true | f0, f1 isolated to it |"
        )
        print("|---|---|---|---|---|")
        rows = []
        for seed in range(start, stop):
            with tempfile.TemporaryDirectory() as tmp:
                got = one_run(scenario, seed, Path(tmp))
            rows.append((got["_mar"]["ratio"], got["f0"]["ratio"], got["f1"]["ratio"]))
            print(
                f"| {seed} | {got['_mar']['ratio']:.2%} | {got['f0']['ratio']:.4f} |"
                f" {got['f1']['ratio']:.4f} | {got['f0']['isolated']:.1%},"
                f" {got['f1']['isolated']:.1%} |",
                flush=True,
            )
        r = np.array(rows)
        within = np.abs(r[:, 1:] - 1.0) <= 0.05
        print(
            f"| mean (range) | {r[:, 0].mean():.2%} |"
            f" {r[:, 1].mean():.4f} ({r[:, 1].min():.4f}-{r[:, 1].max():.4f}) |"
            f" {r[:, 2].mean():.4f} ({r[:, 2].min():.4f}-{r[:, 2].max():.4f}) |"
            f" within 5 %: {int(within[:, 0].sum())}/{len(r)} and {int(within[:, 1].sum())}/{len(r)} |"
        )
    print(f"\nload average at the end: {' '.join(f'{v:.1f}' for v in os.getloadavg())}")


if __name__ == "__main__":
    main()
