"""Measure issue 17's targets on the MIMU4444 recordings (docs/real-arrays.md).

Calibrate on one recording (``--train``, default exp_1), apply to another (``--test``,
default exp_2) with only a 10 s bias calibration at its start, and measure out of sample:

1. accelerometer triad agreement at rest, before and after calibration;
2. per-orientation alarm rates of glt and pca-parity at alpha = 1 % (gyro and accel)
   over the static orientations of the test recording, and in its motion phase with the
   clipped samples excluded; with the calibration and without (nominal geometry only);
3. a 0.9 deg/s gyro step and a 0.05 g accel step injected for 10 s in the middle of every
   static orientation (a different sensor each time): MAR, FIR and FAR of pca-parity and
   glt over the static phase;
4. ``calibrate`` runtime on the training recording.

The recordings are not in the repository (github hcarlsso/Self-Calibration-Inertial-
Sensor-Arrays-BCD.jl, ``experimental_data/calibration/exp_N/data.bin``, MIT licence)::

    python benchmarks/real_arrays.py /path/to/calibration --out results/ [--train exp_1] [--test exp_2]

Prints Markdown tables and writes ``figures.json`` in ``--out``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from imufdi_cli.array import ArrayConfig  # noqa: E402
from imufdi_cli.calibrate import calibrate_file, find_static  # noqa: E402
from imufdi_cli.detect import detect_file  # noqa: E402
from imufdi_cli.faults import inject_file  # noqa: E402
from imufdi_cli.mcapio import read_array  # noqa: E402
from imufdi_cli.pipeline import ingest_file  # noqa: E402
from imufdi_cli.report import build_report  # noqa: E402
from imufdi_cli.validity import apply_calibration  # noqa: E402

LAYOUT = ROOT / "docs" / "layouts" / "mimu4444.toml"
BASE = ROOT / "sample_logs" / "mimu4444-array.toml"
DETECTORS = ("glt", "pca-parity")
CALIBRATION = (0.0, 10.0)
FAULT_S = 10.0


def ingest(data: Path, name: str, out: Path) -> Path:
    path = out / f"{name}.mcap"
    stats = ingest_file(str(data / name / "data.bin"), str(path), layout=str(LAYOUT),
                        array_path=str(BASE))  # fmt: skip
    print(f"ingest {name}: {stats.frames_ok} frames, {stats.frames_bad_checksum} bad checksums,"
          f" {stats.bytes_dropped} bytes dropped", file=sys.stderr)  # fmt: skip
    return path


def static_intervals(path: Path) -> tuple[list[Any], float, np.ndarray, ArrayConfig, Any]:
    array, block = read_array(str(path))
    t = block.t_s()
    intervals, _ = find_static(array, block.accel, block.gyro, t, np.ones(len(t), bool))
    return intervals, float(intervals[-1].end_s), t, array, block


def agreement(
    array: ArrayConfig, block: Any, t: np.ndarray, intervals: list[Any]
) -> dict[str, float]:
    """RMS over static orientations, IMUs and axes of each triad's mean specific force minus
    the array mean (body frame): raw, and after removing each triad's offset measured in
    the first 10 s (what detect's bias calibration does)."""
    means = []
    for item in intervals:
        rows = (t >= max(item.start_s, 0.0)) & (t <= item.end_s)
        means.append(np.einsum("kij,nkj->nki", array.rotations(), block.accel[rows]).mean(0))
    body = np.stack(means)  # (I, m, 3)
    diff = body - body.mean(axis=1, keepdims=True)
    first = (t >= CALIBRATION[0]) & (t < CALIBRATION[1])
    ref = np.einsum("kij,nkj->nki", array.rotations(), block.accel[first]).mean(0)
    ref = ref - ref.mean(axis=0)
    return {
        "rms": float(np.sqrt(np.mean(diff**2))),
        "rms_after_10s_offsets": float(np.sqrt(np.mean((diff - ref) ** 2))),
    }


def alarm_table(detected: Path, intervals: list[Any], motion_start: float) -> dict[str, Any]:
    """Per orientation and in the motion phase: alarm rate per detector and type."""
    table: dict[str, Any] = {}
    for entry in build_report(str(detected)).entries:
        key = f"{entry.detector}.{entry.sensor_type}"
        rates = []
        for item in intervals:
            window = (max(item.start_s, CALIBRATION[1]), item.end_s)
            if window[1] <= window[0]:
                rates.append(None)
                continue
            rates.append(_rate(detected, entry.detector, entry.sensor_type, window))
        motion = _rate(detected, entry.detector, entry.sensor_type, (motion_start, None), True)
        valid = [r for r in rates if r is not None]
        table[key] = {
            "orientations": rates,
            "static_mean": float(np.mean(valid)),
            "static_worst": float(np.max(valid)),
            "motion": motion["rate"],
            "motion_excluded": motion["excluded"],
        }
    return table


_REPORTS: dict[tuple[str, Any], Any] = {}


def _report(path: Path, window: tuple[float, float | None]) -> Any:
    key = (str(path), window)
    if key not in _REPORTS:
        _REPORTS[key] = build_report(str(path), window=window)
    return _REPORTS[key]


def _rate(path: Path, detector: str, sensor_type: str, window: tuple[float, float | None],
          full: bool = False) -> Any:  # fmt: skip
    """Alarm rate of the scored samples in ``window`` (clipped/invalid ones not scored)."""
    entry = _report(path, window).entry(detector, sensor_type)
    rate = entry.metrics.alarm_rate
    if full:
        return {"rate": rate, "excluded": entry.validity.get("excluded", 0)}
    return rate


def injection(
    test: Path, cal: Path, intervals: list[Any], out: Path, array: ArrayConfig
) -> dict[str, Any]:
    specs = []
    for i, item in enumerate(intervals):
        start = max(item.start_s, CALIBRATION[1])
        mid = (start + item.end_s) / 2
        at, until = mid - FAULT_S / 2, mid + FAULT_S / 2
        if at < start:
            continue
        k_g, k_a = i % array.n_imus, (i + 3) % array.n_imus
        axis_g, axis_a = "xyz"[i % 3], "xyz"[(i + 1) % 3]
        specs.append(f"step:imu{k_g}.gyro.{axis_g},at={at:.3f}s,until={until:.3f}s,amp=0.9deg/s")
        specs.append(f"step:imu{k_a}.accel.{axis_a},at={at:.3f}s,until={until:.3f}s,amp=0.05g")
    faulty = out / "faulty.mcap"
    inject_file(str(test), str(faulty), specs, [], seed=0)
    detected = out / "faulty-detect.mcap"
    detect_file(str(faulty), str(detected), [(d, {}) for d in DETECTORS], calibrate=CALIBRATION,
                array=ArrayConfig.load(cal))  # fmt: skip
    static_end = intervals[-1].end_s
    rep = build_report(str(detected), window=(CALIBRATION[1], static_end))
    figures: dict[str, Any] = {"faults": specs}
    for entry in rep.entries:
        m = entry.metrics
        # FAR on the static rows only (the moves between orientations are motion)
        false_alarms = free = 0
        for item in intervals:
            window = (max(item.start_s, CALIBRATION[1]), item.end_s)
            if window[1] > window[0]:
                part = _report(detected, window).entry(entry.detector, entry.sensor_type)
                false_alarms += part.metrics.false_alarms
                free += part.metrics.fault_free_samples
        figures[f"{entry.detector}.{entry.sensor_type}"] = {
            "far_static": false_alarms / free if free else None,
            "far_static_phase": m.far, "mar": m.mar, "fir": m.fir,
            "detection_delay_s": m.detection_delay_s, "faulty_samples": m.faulty_samples,
        }  # fmt: skip
    return figures


def pct(value: Any) -> str:
    return (
        "—"
        if value is None or (isinstance(value, float) and np.isnan(value))
        else f"{100 * value:.2f}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("data", type=Path, help="directory holding exp_N/data.bin")
    parser.add_argument("--train", default="exp_1")
    parser.add_argument("--test", default="exp_2")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument(
        "--runs", default="0,1,2,3,4",
        help="which detection runs (0 nominal, 1 before: glt sigma from the window and no"
        " lever arms, 2 glt sigma from the window, 3 defaults, 4 track_bias=300s)",
    )  # fmt: skip
    args = parser.parse_args()
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    train, test = ingest(args.data, args.train, out), ingest(args.data, args.test, out)

    started, cpu = time.perf_counter(), time.process_time()
    result = calibrate_file(str(train), base=ArrayConfig.load(BASE))
    runtime, cpu = time.perf_counter() - started, time.process_time() - cpu
    cal = out / f"{args.train}-calibrated.toml"
    cal.write_text(result.array.to_toml())
    figures: dict[str, Any] = {
        "calibrate": {
            "runtime_s": runtime,
            "cpu_s": cpu,
            "intervals": len(result.intervals),
            "orientations": result.orientations,
            "coverage": result.coverage,
            "residual_rms": result.residual_rms,
            "warnings": result.warnings,
        }
    }

    intervals, static_end, t, array, block = static_intervals(test)
    motion_start = static_end + 2.0
    calibrated = apply_calibration(block, result.array)
    figures["agreement"] = {
        "before": agreement(array, block, t, intervals),
        "after": agreement(result.array, calibrated, t, intervals),
        "orientations": len(intervals),
    }

    tables = {}
    before = {"glt": {"sigma_source": "calibration", "lever_arm": "false"}}
    window_sigma = {"glt": {"sigma_source": "calibration"}}
    runs: list[tuple[str, ArrayConfig, dict[str, dict[str, Any]]]] = [
        ("nominal", ArrayConfig.load(BASE), {}),
        ("calibrated, glt sigma from the 10 s window, no lever arms", result.array, before),
        ("calibrated, glt sigma from the 10 s window", result.array, window_sigma),
        ("calibrated", result.array, {}),
        ("calibrated, track_bias=300s", result.array,
         {d: {"track_bias": "300s"} for d in DETECTORS}),
    ]  # fmt: skip
    chosen = {int(v) for v in args.runs.split(",")}
    for n, (label, config, params) in enumerate(runs):
        if n not in chosen:
            continue
        detected = out / f"{args.test}-run{n}.mcap"
        detect_file(str(test), str(detected), [(d, dict(params.get(d, {}))) for d in DETECTORS],
                    calibrate=CALIBRATION, array=config)  # fmt: skip
        tables[label] = alarm_table(detected, intervals, motion_start)
    figures["alarm_rates"] = tables
    figures["injection"] = injection(test, cal, intervals, out, result.array)
    (out / "figures.json").write_text(json.dumps(figures, indent=2, default=float))
    print_markdown(figures, args.train, args.test, intervals, motion_start)


def print_markdown(fig: dict[str, Any], train: str, test: str, intervals: list[Any],
                   motion_start: float) -> None:  # fmt: skip
    c = fig["calibrate"]
    print(f"calibrate {train}: {c['intervals']} static intervals, {c['orientations']} orientations,"
          f" coverage {c['coverage']:.2f}, runtime {c['runtime_s']:.2f} s wall, {c['cpu_s']:.2f} s CPU"
          f" (reading the log included); residual RMS between"
          f" triads: accel {c['residual_rms']['accel'][0]:.4f} -> {c['residual_rms']['accel'][1]:.4f}"
          f" m/s^2 (at rest), gyro {np.degrees(c['residual_rms']['gyro'][0]):.2f} ->"
          f" {np.degrees(c['residual_rms']['gyro'][1]):.2f} deg/s (motion)\n")  # fmt: skip
    a = fig["agreement"]
    print(
        f"Accelerometer triad agreement at rest on {test} ({a['orientations']} orientations), m/s^2 RMS:\n"
    )
    print("| | raw | after removing the 0-10 s offsets |\n|---|---|---|")
    for label in ("before", "after"):
        print(
            f"| {label} calibration | {a[label]['rms']:.4f} | {a[label]['rms_after_10s_offsets']:.4f} |"
        )
    for label, table in fig["alarm_rates"].items():
        keys = list(table)
        print(f"\nAlarm rate % on {test}, {label} array, --calibrate 0s:10s, alpha = 1 %:\n")
        print("| orientation | window s | " + " | ".join(keys) + " |")
        print("|---|---|" + "---|" * len(keys))
        for i, item in enumerate(intervals):
            cells = [pct(table[k]["orientations"][i]) for k in keys]
            print(
                f"| {i + 1} | {max(item.start_s, CALIBRATION[1]):.0f}-{item.end_s:.0f} | "
                + " | ".join(cells)
                + " |"
            )
        print(
            "| **mean of static** | | "
            + " | ".join(pct(table[k]["static_mean"]) for k in keys)
            + " |"
        )
        print(
            "| **worst static** | | "
            + " | ".join(pct(table[k]["static_worst"]) for k in keys)
            + " |"
        )
        print(f"| **motion** | {motion_start:.0f}- | " + " | ".join(
            f"{pct(table[k]['motion'])} ({table[k]['motion_excluded']} excl.)" for k in keys) + " |")  # fmt: skip
    inj = fig["injection"]
    print(f"\nInjected steps ({len(inj['faults']) // 2} gyro 0.9 deg/s + {len(inj['faults']) // 2}"
          f" accel 0.05 g, {FAULT_S:g} s each, one per static orientation), static phase:\n")  # fmt: skip
    print(
        "| detector.type | FAR % (static rows) | FAR % (static phase, moves included) | MAR % | FIR % | delay s |"
    )
    print("|---|---|---|---|---|---|")
    for key, v in inj.items():
        if key == "faults":
            continue
        delay = "—" if v["detection_delay_s"] is None else f"{v['detection_delay_s']:.3f}"
        print(f"| {key} | {pct(v['far_static'])} | {pct(v['far_static_phase'])} | {pct(v['mar'])}"
              f" | {pct(v['fir'])} | {delay} |")  # fmt: skip


if __name__ == "__main__":
    main()
