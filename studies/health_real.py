"""The health detector under a false-alarm budget on the real MIMU4444 recordings' rest.

Each recording's static stretches (every gyro below 3 deg/s, 1 s trimmed at each end, at
least 5 s long) are the fault-free data: health is calibrated on the first 10 s of the
first stretch, then every stretch (the first after those 10 s) is tested from a fresh
state at ``--false-alarms`` (1/h by default); the episodes (alarm runs merged across
gaps of up to 0.1 s, as ``imufdi report`` merges them) are counted per sensor type
(docs/algorithms/health.md, "Real MEMS data").

The recordings are not in the repository (github hcarlsso/Self-Calibration-Inertial-
Sensor-Arrays-BCD.jl, ``experimental_data/calibration/exp_N/data.bin``)::

    python studies/health_real.py /path/to/calibration --runs exp_1,exp_2 --out results/

exp_1 and exp_2 were used to choose the design; exp_3 and exp_4 to evaluate it;
exp_5 to exp_10 are held out: the script refuses them.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from imufdi_cli.detectors import make_detector  # noqa: E402
from imufdi_cli.episodes.episode import find_episodes  # noqa: E402
from imufdi_cli.mcapio import read_array  # noqa: E402
from studies.budget_real import prepare  # noqa: E402

STILL_DEG_S = 3.0
TRIM_S = 1.0
SHORTEST_S = 5.0
CALIBRATION_S = 10.0
MERGE_GAP_S = 0.1


def stretches(t: np.ndarray, gyro: np.ndarray) -> list[tuple[int, int]]:
    """Row ranges [a, b) where every gyro reads below STILL_DEG_S, trimmed, long enough."""
    still = np.all(np.abs(np.degrees(gyro)) < STILL_DEG_S, axis=(1, 2))
    edges = np.flatnonzero(np.diff(np.r_[0, still.astype(int), 0]))
    out = []
    for a, b in zip(edges[::2], edges[1::2]):
        a2 = int(np.searchsorted(t, t[a] + TRIM_S))
        b2 = int(np.searchsorted(t, t[b - 1] - TRIM_S))
        if b2 > a2 and t[b2 - 1] - t[a2] >= SHORTEST_S:
            out.append((a2, b2))
    return out


def run(log: Path, budget: str) -> dict[str, object]:
    array, block = read_array(str(log))
    t = block.t_s()
    spans = stretches(t, block.gyro)
    a0, _ = spans[0]
    c1 = int(np.searchsorted(t, t[a0] + CALIBRATION_S))
    detector = make_detector("health", {"false_alarms": budget})
    detector.fit(block.slice(a0, c1), array)
    counts: dict[str, int] = {}
    tested = 0.0
    for k, (a, b) in enumerate(spans):
        start = c1 if k == 0 else a
        if b - start < 2:
            continue
        fresh = copy.deepcopy(detector)
        out = fresh.process(block.slice(start, b))
        tested += float(t[b - 1] - t[start])
        for sensor_type, decisions in out.items():
            # alarm runs merged across gaps of up to 0.1 s, as report merges episodes
            runs = find_episodes(decisions.alarm, merge_gap=round(MERGE_GAP_S * array.rate_hz))
            counts[sensor_type] = counts.get(sensor_type, 0) + len(runs)
    return {"stretches": len(spans), "tested_s": tested, "episodes": counts}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("data", type=Path, help="directory holding exp_N/data.bin")
    parser.add_argument("--runs", default="exp_1,exp_2", help="comma list, e.g. exp_3,exp_4")
    parser.add_argument("--false-alarms", default="1/h")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    results = {}
    for name in args.runs.split(","):
        results[name] = run(prepare(args.data, name, args.out), args.false_alarms)
        row = results[name]
        print(f"{name}: {row['stretches']} stretches, {row['tested_s']:.0f} s tested,"
              f" episodes {row['episodes']}")  # fmt: skip
    (args.out / "health_real.json").write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
