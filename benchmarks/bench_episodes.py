"""Alarm-episode explanations: fault class and size intervals on fresh seeds, and cost.

Usage: python benchmarks/bench_episodes.py [--seeds 7000:7020] [--detector glt]

For each seed (evaluation seeds: no choice in imufdi_cli/episodes.py was made on them;
the method was developed on seeds 0-5) a 20 s paper-table4 log is simulated, and one fault
per model is injected on a sensor drawn from the seed at a jittered onset in [8, 9) s:

    step 0.9 deg/s, drift 10 deg/s^2, noise x3 (4 s), stuck (4 s), spikes 5 Hz of 3 deg/s (4 s)

``imufdi detect`` (library) writes the explained episodes; they are matched to the truth
(:func:`imufdi_cli.episodes.match_episodes`) and scored: per true model, the share of
matched episodes whose class is right, and the share whose 90 % size interval covers the
injected size (targets: class >= 90 %, coverage 85-95 %). False episodes per hour come
from the fault-free seconds after the calibration window. Also prints detect's time with and without explanations on
the same logs (a ratio, same run) and the load average.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from imufdi_cli.detect import detect_file
from imufdi_cli.episodes import match_episodes
from imufdi_cli.faults import inject_file
from imufdi_cli.mcapio import McapSource, read_events
from imufdi_cli.pipeline import simulate_file
from imufdi_cli.report import truth_windows

FAULTS = {
    "step": "step:{s},at={at}s,amp=0.9deg/s",
    "drift": "drift:{s},at={at}s,rate=10deg/s^2",
    "noise": "noise:{s},at={at}s,duration=4s,factor=3",
    "stuck": "stuck:{s},at={at}s,duration=4s",
    "spikes": "spikes:{s},at={at}s,duration=4s,rate=5Hz,amp=3deg/s",
}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", default="7000:7020")
    parser.add_argument("--detector", default="glt")
    args = parser.parse_args()
    lo, hi = (int(x) for x in args.seeds.split(":"))
    rows: dict[str, list[dict]] = defaultdict(list)
    false_episodes, fault_free_hours = 0, 0.0
    time_on = time_off = 0.0
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        for seed in range(lo, hi):
            base = str(work / f"s{seed}.mcap")
            simulate_file("paper-table4", base, seed=seed, options={"duration": 20.0})
            rng = np.random.default_rng(seed)
            for model, spec in FAULTS.items():
                sensor = f"imu{rng.integers(16)}.gyro.{'xyz'[rng.integers(3)]}"
                at = 8.0 + rng.random()
                faulty = str(work / "f.mcap")
                inject_file(base, faulty, [spec.format(s=sensor, at=f"{at:.3f}")], [], seed=seed)
                out = str(work / "d.mcap")
                start = time.perf_counter()
                detect_file(faulty, out, [(args.detector, {})], explain=False)
                time_off += time.perf_counter() - start
                start = time.perf_counter()
                detect_file(faulty, out, [(args.detector, {})])
                time_on += time.perf_counter() - start
                with McapSource(out) as src:
                    list(src.batches())
                    truth = truth_windows(dict(src.metadata))
                assert truth is not None
                faults = [
                    {**d, "start_ns": w.start_ns, "end_ns": w.end_ns}
                    for w, d in zip(truth.windows, truth.descriptions)
                ]
                episodes = [
                    e["episode"]
                    for _, e in read_events(out, "/imufdi/events")
                    if e["event"] == "episode" and e["sensor_type"] == "gyro"
                ]
                matches = match_episodes(episodes, faults)
                # out-of-sample fault-free time: after the 2 s calibration window (the
                # detector was fitted on it), before the onset
                onset_ns = faults[0]["start_ns"]
                calibrated_ns = onset_ns - round((at - 2.0) * 1e9)
                for episode, match in zip(episodes, matches):
                    if match["match"] == "fault":
                        rows[model].append({**match, "class": episode["fault_class"]})
                    elif (
                        match["match"] == "false"
                        and episode["start_ns"] >= calibrated_ns
                        and episode["end_ns"] < onset_ns
                    ):
                        false_episodes += 1
                fault_free_hours += (at - 2.0) / 3600
            print(f"seed {seed} done", file=sys.stderr, flush=True)
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    print(f"detector {args.detector}, paper-table4 gyro, seeds {lo}-{hi - 1}; load average {load}")
    print(f"{'model':8s} {'matched':>8s} {'class right':>12s} {'coverage':>9s}  classes found")
    for model in FAULTS:
        got = rows[model]
        n = len(got)
        right = sum(r["class_right"] for r in got)
        sized = [r for r in got if r["covered"] is not None]
        cov = sum(r["covered"] for r in sized) / len(sized) if sized else float("nan")
        found: dict[str, int] = defaultdict(int)
        for r in got:
            found[r["class"]] += 1
        print(
            f"{model:8s} {n:8d} {100 * right / max(n, 1):11.1f}% {100 * cov:8.1f}%  {dict(found)}"
        )
    print(
        "false episodes between calibration and onset:"
        f" {false_episodes / fault_free_hours:.0f} per hour"
    )
    print(f"detect time with explanations / without: {time_on / time_off:.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
