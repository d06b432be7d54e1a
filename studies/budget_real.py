"""Decisions under a false-alarm budget on the real MIMU4444 recordings.

Calibrate on one recording (``--train``), test the others (``--test``) with a bias window
at their start (``--calibrate``, 1-10 s by default: the board is static there), every
detector under the budget (``--false-alarms``, 1/h by default), and measure out of sample:

1. false alarm episodes of each status channel at rest (inside the static orientations
   ``imufdi calibrate`` finds, 0.5 s in from their ends), in the transitions between them,
   and in the hand motion after the last orientation; with the tested minutes and the
   exact Poisson 95 % upper bound of the rate per hour (the recordings are short: 8 min
   at rest and about 100 s of motion each);
2. at rest, a 0.9 deg/s gyro step and a 0.05 g accel step for 10 s in the middle of every
   static orientation after the bias window (each on another sensor): detected or not,
   detection delay, isolated to the right sensor;
3. in the hand motion, a 5 deg/s gyro step and a 0.2 g accel step for 10 s at three
   onsets (each on another sensor), the same figures.

The recordings are not in the repository (github hcarlsso/Self-Calibration-Inertial-
Sensor-Arrays-BCD.jl, ``experimental_data/calibration/exp_N/data.bin``, MIT licence)::

    python studies/budget_real.py /path/to/calibration --train exp_1 --test exp_2 --out results/

exp_1 and exp_2 were used to develop the budgeted tests; exp_3 and exp_4 to evaluate
them (docs/real-arrays.md); exp_5 to exp_10 are held out: the script refuses them.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from imufdi_cli.array import ArrayConfig  # noqa: E402
from imufdi_cli.calibrate import calibrate_file, find_static  # noqa: E402
from imufdi_cli.detect import detect_file  # noqa: E402
from imufdi_cli.faults import inject_file  # noqa: E402
from imufdi_cli.mcapio import read_array, read_status  # noqa: E402
from imufdi_cli.pipeline import ingest_file  # noqa: E402
from imufdi_cli.report import build_report  # noqa: E402

LAYOUT = ROOT / "docs" / "layouts" / "mimu4444.toml"
BASE = ROOT / "imufdi_cli" / "sample_logs" / "mimu4444-array.toml"
HELD_OUT = {f"exp_{k}" for k in range(5, 11)}
MARGIN_S = 0.5
FAULT_S = 10.0


def poisson_upper(count: int, hours: float, level: float = 0.95) -> float:
    """Exact one-sided upper bound of a Poisson rate per hour: chi2_level(2k + 2) / 2T."""
    from scipy.stats import chi2

    return float(chi2.ppf(level, 2 * count + 2) / 2.0 / hours) if hours > 0 else math.inf


def prepare(data: Path, name: str, out: Path) -> Path:
    if name in HELD_OUT:
        raise SystemExit(f"{name} is held out: run nothing on exp_5 .. exp_10")
    path = out / f"{name}.mcap"
    if not path.exists():
        ingest_file(str(data / name / "data.bin"), str(path), layout=str(LAYOUT),
                    array_path=str(BASE))  # fmt: skip
    return path


def phases(path: Path) -> tuple[list[tuple[float, float]], float, float]:
    """Static orientations (s from the first sample), motion start and log end."""
    array, block = read_array(str(path))
    t = block.t_s()
    intervals, _ = find_static(array, block.accel, block.gyro, t, np.ones(len(t), bool))
    spans = [(float(i.start_s), float(i.end_s)) for i in intervals]
    return spans, spans[-1][1] + 2.0, float(t[-1] - t[0])


def episodes(detected: Path, spans: list[tuple[float, float]], motion: float,
             start: float) -> dict[str, Any]:  # fmt: skip
    """False alarm episodes (alarm starts) per channel at rest, in transitions and in
    motion, with the tested minutes (samples with a finite threshold, after ``start``)."""
    table: dict[str, Any] = {}
    for (det, kind), status in sorted(read_status(str(detected)).items()):
        rel = (status.t_ns - status.t_ns[0]) / 1e9
        alarm = status.alarm
        starts = alarm & ~np.concatenate([[False], alarm[:-1]])
        tested = (rel >= start) & np.isfinite(status.threshold)
        rest = np.zeros(rel.size, bool)
        for a, b in spans:
            rest |= (rel >= a + MARGIN_S) & (rel < b - MARGIN_S)
        moving = rel >= motion
        dt = float(np.median(np.diff(rel)))
        row: dict[str, Any] = {}
        for phase, mask in (("rest", rest), ("transitions", ~rest & ~moving), ("motion", moving)):
            use = mask & tested
            count = int(np.count_nonzero(starts & use))
            minutes = float(np.count_nonzero(use) * dt / 60.0)
            row[phase] = {
                "episodes": count,
                "minutes": minutes,
                "per_hour": count / (minutes / 60.0) if minutes else None,
                "upper95_per_hour": poisson_upper(count, minutes / 60.0),
                "alarm_share": float(alarm[use].mean()) if use.any() else None,
            }
        table[f"{det}.{kind}"] = row
    return table


def fault_specs(array: ArrayConfig, spans: list[tuple[float, float]], motion: float,
                end: float, start: float) -> tuple[list[str], list[str]]:  # fmt: skip
    rest, moving = [], []
    for i, (a, b) in enumerate(spans):
        a = max(a, start)
        mid = (a + b) / 2.0
        if mid - FAULT_S / 2 < a or mid + FAULT_S / 2 > b:
            continue
        at, until = mid - FAULT_S / 2, mid + FAULT_S / 2
        gyro = f"imu{i % array.n_imus}.gyro.{'xyz'[i % 3]}"
        accel = f"imu{(i + 3) % array.n_imus}.accel.{'xyz'[(i + 1) % 3]}"
        rest.append(f"step:{gyro},at={at:.3f}s,until={until:.3f}s,amp=0.9deg/s")
        rest.append(f"step:{accel},at={at:.3f}s,until={until:.3f}s,amp=0.05g")
    for j, at in enumerate(np.linspace(motion + 5.0, end - FAULT_S - 5.0, 3)):
        until = at + FAULT_S
        gyro = f"imu{(2 * j + 1) % array.n_imus}.gyro.{'zxy'[j % 3]}"
        accel = f"imu{(2 * j + 4) % array.n_imus}.accel.{'yzx'[j % 3]}"
        moving.append(f"step:{gyro},at={at:.3f}s,until={until:.3f}s,amp=5deg/s")
        moving.append(f"step:{accel},at={at:.3f}s,until={until:.3f}s,amp=0.2g")
    return rest, moving


def fault_figures(test: Path, specs: list[str], cal: ArrayConfig, detectors: list[str],
                  budget: float, window: tuple[float, float], out: Path,
                  tag: str) -> dict[str, Any]:  # fmt: skip
    faulty = out / f"{test.stem}-{tag}.mcap"
    inject_file(str(test), str(faulty), specs, [], seed=0)
    detected = out / f"{test.stem}-{tag}-detect.mcap"
    detect_file(str(faulty), str(detected), [(d, {}) for d in detectors], calibrate=window,
                array=cal, false_alarms=budget, explain=False, window=(window[1], None))  # fmt: skip
    figures: dict[str, Any] = {}
    for entry in build_report(str(detected)).entries:
        rows = []
        for fault in entry.metrics.faults:
            rows.append({
                "fault": fault.fault_id,
                "detected": bool(fault.detected),
                "delay_s": fault.detection_delay_s,
                "isolation_delay_s": fault.isolation_delay_s,
                "isolated_correctly": fault.isolated_correctly,
            })  # fmt: skip
        delays = [r["delay_s"] for r in rows if r["delay_s"] is not None]
        figures[f"{entry.detector}.{entry.sensor_type}"] = {
            "faults": len(rows),
            "detected": sum(r["detected"] for r in rows),
            "delay_median_s": float(np.median(delays)) if delays else None,
            "delay_max_s": float(np.max(delays)) if delays else None,
            "right_sensor": [r["isolated_correctly"] for r in rows],
            "fir": entry.metrics.fir,
            "rows": rows,
        }
    return figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("data", type=Path, help="directory holding exp_N/data.bin")
    parser.add_argument("--train", default="exp_1")
    parser.add_argument("--test", default="exp_2", help="comma list, e.g. exp_3,exp_4")
    parser.add_argument("--detectors", default="glt,pca-parity")
    parser.add_argument("--false-alarms", default="1/h")
    parser.add_argument("--calibrate", default="1s:10s")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    from imufdi_cli.units import parse_quantity, parse_time_range

    budget = parse_quantity(args.false_alarms, "frequency", name="--false-alarms")
    window = parse_time_range(args.calibrate, name="--calibrate")
    assert window[1] is not None
    detectors = args.detectors.split(",")
    args.out.mkdir(parents=True, exist_ok=True)
    train = prepare(args.data, args.train, args.out)
    cal_path = args.out / f"{args.train}-calibrated.toml"
    if not cal_path.exists():
        cal_path.write_text(calibrate_file(str(train), base=ArrayConfig.load(BASE)).array.to_toml())
    cal = ArrayConfig.load(str(cal_path))
    results: dict[str, Any] = {"train": args.train, "false_alarms_per_hour": budget * 3600}
    for name in args.test.split(","):
        test = prepare(args.data, name, args.out)
        spans, motion, end = phases(test)
        clean = args.out / f"{name}-detect.mcap"
        detect_file(str(test), str(clean), [(d, {}) for d in detectors], calibrate=window,
                    array=cal, false_alarms=budget, explain=False)  # fmt: skip
        rest_specs, motion_specs = fault_specs(cal, spans, motion, end, window[1])
        results[name] = {
            "false_alarms": episodes(clean, spans, motion, window[1]),
            "rest_faults": fault_figures(
                test, rest_specs, cal, detectors, budget, window, args.out, "rest"
            ),
            "motion_faults": fault_figures(
                test, motion_specs, cal, detectors, budget, window, args.out, "motion"
            ),
        }
        print(f"\n## {args.train} -> {name} at {args.false_alarms}\n")
        print("| channel | rest: episodes / min (95 % UB /h) | transitions | motion |")
        print("|---|---|---|---|")
        for key, row in results[name]["false_alarms"].items():
            cells = [f"{row[p]['episodes']} / {row[p]['minutes']:.1f} ({row[p]['upper95_per_hour']:.1f})"
                     for p in ("rest", "transitions", "motion")]  # fmt: skip
            print(f"| {key} | " + " | ".join(cells) + " |")
        for tag in ("rest_faults", "motion_faults"):
            print(f"\n{tag}: detected / faults, median and max delay (s), right sensor")
            for key, row in results[name][tag].items():
                print(f"  {key}: {row['detected']}/{row['faults']}, {row['delay_median_s']},"
                      f" {row['delay_max_s']}, {row['right_sensor']}")  # fmt: skip
    (args.out / "budget_real.json").write_text(json.dumps(results, indent=1, default=str))


if __name__ == "__main__":
    main()
