"""cnn-map on a real MIMU4444 recording, calibrated on its hand motion (docs/algorithms/cnn-map.md).

The mapping needs a calibration window with motion; the MIMU4444 recordings
move only after their 20 static orientations. So cnn-map is calibrated on a motion
window (default 520-560 s of exp_2) and its accelerometer alarm rate is measured out of
that window: on each static orientation (found by ``calibrate``'s ``find_static``, all
before the motion), on the motion out of the window (and per 10 s after it), and the MAR of
accelerometer noise growths injected at rest (x3 and x10 of a 0.02 m/s^2 nominal sigma, 10 s
each in orientations 5 and 13, the default mode only). Clipped samples are not scored.

Needs the ingested recording and the chip calibration of another one, as
``studies/real_arrays.py`` leaves them::

    python studies/real_arrays.py /work/data/mimu4444 --test exp_2 --out DIR --runs 3 \
        --detectors glt --rates-only
    python studies/real_cnn_map.py DIR [--test exp_2] [--train exp_1] [--calibrate 520 560]

Prints a Markdown table and writes ``cnn-map-<test>.json`` in DIR.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from imufdi_cli.array import ArrayConfig  # noqa: E402
from imufdi_cli.calibrate import find_static  # noqa: E402
from imufdi_cli.detect import detect_file  # noqa: E402
from imufdi_cli.faults import inject_file  # noqa: E402
from imufdi_cli.mcapio import read_array  # noqa: E402
from imufdi_cli.report import build_report  # noqa: E402

#: injected at rest: (orientation index, sensor, factor over sigma0 = 0.02 m/s^2)
INJECTED = ((4, "imu2.accel.x", 3.0), (12, "imu5.accel.y", 10.0))


def rate(path: Path, window: tuple[float, float | None]) -> tuple[float, int]:
    """Accel alarm rate of cnn-map over the scored samples in ``window``, and their count."""
    entry = build_report(str(path), window=window).entry("cnn-map", "accel")
    alarm_rate = entry.metrics.alarm_rate
    return (math.nan if alarm_rate is None else float(alarm_rate)), int(entry.metrics.samples)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dir", type=Path)
    parser.add_argument("--test", default="exp_2")
    parser.add_argument("--train", default="exp_1")
    parser.add_argument("--calibrate", type=float, nargs=2, default=(520.0, 560.0))
    parser.add_argument("--modes", nargs="+", default=["report", "alarm"])
    args = parser.parse_args()
    log = args.dir / f"{args.test}.mcap"
    array = ArrayConfig.load(args.dir / f"{args.train}-calibrated.toml")
    raw_array, block = read_array(str(log))
    t = block.t_s()
    intervals, _ = find_static(raw_array, block.accel, block.gyro, t, np.ones(len(t), bool))
    motion_start = float(intervals[-1].end_s)
    cal = (float(args.calibrate[0]), float(args.calibrate[1]))
    figures: dict[str, Any] = {"calibrate_s": cal, "load_average": os.getloadavg()[0]}
    for mode in args.modes:
        out = args.dir / f"cnn-map-{args.test}-{mode}.mcap"
        start = time.perf_counter()
        detect_file(str(log), str(out), [("cnn-map", {"mapping_test": mode})],
                    calibrate=cal, array=array)  # fmt: skip
        seconds = time.perf_counter() - start
        static = [rate(out, (item.start_s, item.end_s)) for item in intervals]
        before = rate(out, (motion_start, cal[0]))
        after = rate(out, (cal[1], None))
        rates = [r for r, _ in static]
        figures[mode] = {
            "detect_s": seconds,
            "orientations": rates,
            "static_mean": float(np.mean(rates)),
            "static_worst": float(np.max(rates)),
            "motion_out_of_window": (before[0] * before[1] + after[0] * after[1])
            / max(before[1] + after[1], 1),
            "motion_samples": before[1] + after[1],
            "static_samples": int(sum(n for _, n in static)),
        }
    first = args.modes[0]
    out = args.dir / f"cnn-map-{args.test}-{first}.mcap"
    figures[first]["motion_per_10s"] = {
        f"{a:g}": rate(out, (a, a + 10.0))[0] for a in np.arange(cal[1], float(t[-1]), 10.0)
    }
    faults, windows = [], []
    for index, sensor, factor in INJECTED:
        item = intervals[index]
        mid = 0.5 * (item.start_s + item.end_s)
        windows.append((mid - 5.0, mid + 5.0))
        faults.append(f"noise:{sensor},at={mid - 5.0:.3f}s,until={mid + 5.0:.3f}s,"
                      f"factor={factor:g},sigma0=0.02m/s^2")  # fmt: skip
    injected = args.dir / f"cnn-map-{args.test}-injected.mcap"
    inject_file(str(log), str(injected), faults, [], seed=0)
    detected = args.dir / f"cnn-map-{args.test}-injected-detected.mcap"
    detect_file(str(injected), str(detected), [("cnn-map", {"mapping_test": first})],
                calibrate=cal, array=array)  # fmt: skip
    figures[first]["injected_mar"] = {
        spec: build_report(str(detected), window=w).entry("cnn-map", "accel").metrics.mar
        for spec, w in zip(faults, windows)
    }
    (args.dir / f"cnn-map-{args.test}.json").write_text(json.dumps(figures, indent=1) + "\n")
    print(f"cnn-map on {args.test} (chips calibrated on {args.train}), calibrated on"
          f" {cal[0]:g}-{cal[1]:g} s; accel alarm %; load {figures['load_average']:.2f}")  # fmt: skip
    print("\n| mapping_test | static mean | static worst | motion (out of window) | detect s |"
          "\n|---|---|---|---|---|")  # fmt: skip
    for mode in args.modes:
        f = figures[mode]
        print(f"| {mode} | {100 * f['static_mean']:.2f} | {100 * f['static_worst']:.2f} |"
              f" {100 * f['motion_out_of_window']:.2f} | {f['detect_s']:.0f} |")  # fmt: skip
    print("\nper orientation (" + first + "): "
          + ", ".join(f"{100 * r:.2f}" for r in figures[first]["orientations"]))  # fmt: skip
    print("motion per 10 s from " + f"{cal[1]:g} s: "
          + ", ".join(f"{100 * r:.1f}" for r in figures[first]["motion_per_10s"].values()))  # fmt: skip
    for spec, mar in figures[first]["injected_mar"].items():
        print(f"injected {spec}: MAR {mar}")


if __name__ == "__main__":
    main()
