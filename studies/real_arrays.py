"""Measure the real-array targets on the MIMU4444 recordings (docs/real-arrays.md).

Calibrate on one recording (``--train``, default exp_1), apply to another (``--test``,
default exp_2) with only a 10 s bias calibration at its start, and measure out of sample:

1. accelerometer triad agreement at rest, before and after calibration;
2. per-orientation alarm rates of glt and pca-parity at alpha = 1 % (gyro and accel)
   over the static orientations of the test recording, and in its motion phase with the
   clipped samples excluded; with the calibration and without (nominal geometry only);
3. a 0.9 deg/s gyro step and a 0.05 g accel step injected for 10 s in the middle of every
   static orientation (a different sensor each time): MAR, FIR and FAR of pca-parity and
   glt over the static phase;
4. ``calibrate`` runtime on the training recording;
5. the price of the sampling-time jitter model (ArrayConfig ``[jitter]``,
   imufdi_cli/maths/jitter.py): glt's smallest detectable step (50 % per-sample
   detection at alpha = 1 %) at rest and in the motion phase (median and 90th percentile
   of the widening), and steps of that median size injected in the motion phase (their
   glt MAR should be near 50 %).

The recordings are not in the repository (github hcarlsso/Self-Calibration-Inertial-
Sensor-Arrays-BCD.jl, ``experimental_data/calibration/exp_N/data.bin``, MIT licence)::

    python studies/real_arrays.py /path/to/calibration --out results/ [--train exp_1] [--test exp_2]

Prints Markdown tables and writes ``figures.json`` in ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
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
from imufdi_cli.maths.jitter import array_inflation, minimum_detectable_step  # noqa: E402
from imufdi_cli.maths.rigid import accel_design  # noqa: E402
from imufdi_cli.mcapio import read_array  # noqa: E402
from imufdi_cli.pipeline import ingest_file  # noqa: E402
from imufdi_cli.report import build_report  # noqa: E402
from imufdi_cli.validity import apply_calibration  # noqa: E402

LAYOUT = ROOT / "docs" / "layouts" / "mimu4444.toml"
BASE = ROOT / "imufdi_cli" / "sample_logs" / "mimu4444-array.toml"
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


def _design(array: ArrayConfig, sensor_type: str) -> np.ndarray:
    return accel_design(array, sensor_type) if sensor_type == "accel" else (
        array.measurement_matrix(sensor_type))  # fmt: skip


def jitter_price(test: Path, cal_array: ArrayConfig, motion_start: float,
                 out: Path) -> dict[str, Any]:  # fmt: skip
    """glt's smallest detectable step at rest and in motion under the jitter model, and an
    injected check in the motion phase (see the module docstring, item 5)."""
    from imufdi_cli.validity import flag_values

    _, block = read_array(str(test))
    t = block.t_s()
    calibrated = apply_calibration(block, cal_array)
    figures: dict[str, Any] = {}
    specs = []
    motion_rows = t >= motion_start
    clipped = np.zeros(len(t), dtype=bool)
    for s in ("gyro", "accel"):
        c, i = flag_values(block.get(s), s, cal_array.range.get(s))
        clipped |= (c | i).any(axis=(1, 2))
    for s in ("gyro", "accel"):
        H = _design(cal_array, s)
        sigma = cal_array.sensor_noise(s)
        inflation = array_inflation(cal_array, s, H)
        if sigma is None:
            continue
        values = cal_array.select(calibrated.get(s), s)
        factors = np.ones(len(t)) if inflation is None else inflation.factors(values, block.t_ns)
        rows = motion_rows & ~clipped & ~np.roll(clipped, 1)
        dof = H.shape[0] - H.shape[1]
        white = H / sigma[:, None]
        energy = np.diag(np.eye(H.shape[0]) - white @ np.linalg.pinv(white))  # P_jj
        rest = np.array([minimum_detectable_step(e, dof, 0.01) for e in energy]) * sigma
        median, p90 = np.percentile(factors[rows], [50, 90])
        k = int(np.argmin(np.abs(rest - np.median(rest))))  # a typical sensor
        moving = minimum_detectable_step(energy[k], dof, 0.01, median) * sigma[k]
        figures[s] = {
            "rest_median": float(np.median(rest)),
            "motion_median_widening": float(np.sqrt(median)),
            "motion_p90_widening": float(np.sqrt(p90)),
            "motion_median": float(np.median(rest) * np.sqrt(median)),
            "motion_p90": float(np.median(rest) * np.sqrt(p90)),
            "sensor": cal_array.sensor_ids(s)[k],
            "injected_amplitude": float(moving),
        }
        end = float(t[-1])
        for at in np.linspace(motion_start + 5.0, end - 10.0, 6):
            specs.append(f"step:{figures[s]['sensor']},at={at:.3f}s,until={at + 5.0:.3f}s,"
                         f"amp={float(moving)!r}")  # fmt: skip
    faulty = out / "motion-faulty.mcap"
    inject_file(str(test), str(faulty), specs, [], seed=0)
    detected = out / "motion-faulty-detect.mcap"
    detect_file(str(faulty), str(detected), [("glt", {})], calibrate=CALIBRATION,
                array=cal_array)  # fmt: skip
    rep = build_report(str(detected), window=(motion_start, None))
    for entry in rep.entries:
        if entry.sensor_type in figures:
            figures[entry.sensor_type]["injected_mar"] = entry.metrics.mar
            figures[entry.sensor_type]["injected_far"] = entry.metrics.far
    figures["faults"] = specs
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
        help="which detection runs (0 nominal, 1 calibrated without the jitter model, 2 jitter"
        " fitted by moments, 3 defaults (jitter fitted for the level), 4 track_bias=300s, 5 as 3"
        " without the noise spread of calibrate)",
    )  # fmt: skip
    parser.add_argument(
        "--detectors", default=",".join(DETECTORS),
        help="detectors whose alarm rates are tabulated (default glt,pca-parity; any registry"
        " name, e.g. bank,noise-glr,woa-mvmd-glt,px4-selector,ap-consistency)",
    )  # fmt: skip
    parser.add_argument(
        "--rates-only", action="store_true",
        help="only calibrate and tabulate alarm rates (skip the injected steps and the jitter price)",
    )  # fmt: skip
    args = parser.parse_args()
    detectors = tuple(d.strip() for d in args.detectors.split(",") if d.strip())
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
            "jitter_s": result.jitter_s,
            "load_average": os.getloadavg()[0],
        }
    }
    moments = calibrate_file(str(train), base=ArrayConfig.load(BASE), jitter_fit="moments")
    figures["calibrate"]["jitter_s_moments"] = moments.jitter_s

    intervals, static_end, t, array, block = static_intervals(test)
    motion_start = static_end + 2.0
    calibrated = apply_calibration(block, result.array)
    figures["agreement"] = {
        "before": agreement(array, block, t, intervals),
        "after": agreement(result.array, calibrated, t, intervals),
        "orientations": len(intervals),
    }

    tables = {}
    runs: list[tuple[str, ArrayConfig, dict[str, dict[str, Any]]]] = [
        ("nominal", ArrayConfig.load(BASE), {}),
        ("calibrated, no jitter model", result.array.with_jitter({}), {}),
        ("calibrated, jitter fitted by moments", moments.array, {}),
        ("calibrated", result.array, {}),
        ("calibrated, track_bias=300s", result.array,
         {d: {"track_bias": "300s"} for d in DETECTORS if d in detectors}),
        ("calibrated, no noise spread", result.array.with_noise_spread(
            [{} for _ in range(result.array.n_imus)]), {}),
    ]  # fmt: skip
    chosen = {int(v) for v in args.runs.split(",")}
    for n, (label, config, params) in enumerate(runs):
        if n not in chosen:
            continue
        detected = out / f"{args.test}-run{n}.mcap"
        detect_file(str(test), str(detected), [(d, dict(params.get(d, {}))) for d in detectors],
                    calibrate=CALIBRATION, array=config)  # fmt: skip
        tables[label] = alarm_table(detected, intervals, motion_start)
    figures["alarm_rates"] = tables
    if not args.rates_only:
        figures["injection"] = injection(test, cal, intervals, out, result.array)
        figures["jitter_price"] = jitter_price(test, result.array, motion_start, out)
    (out / "figures.json").write_text(json.dumps(figures, indent=2, default=float))
    print_markdown(figures, args.train, args.test, intervals, motion_start)


def print_markdown(fig: dict[str, Any], train: str, test: str, intervals: list[Any],
                   motion_start: float) -> None:  # fmt: skip
    c = fig["calibrate"]
    print(f"calibrate {train}: {c['intervals']} static intervals, {c['orientations']} orientations,"
          f" coverage {c['coverage']:.2f}, runtime {c['runtime_s']:.2f} s wall, {c['cpu_s']:.2f} s CPU"
          f" at load average {c['load_average']:.1f}"
          f" (reading the log included); residual RMS between"
          f" triads: accel {c['residual_rms']['accel'][0]:.4f} -> {c['residual_rms']['accel'][1]:.4f}"
          f" m/s^2 (at rest), gyro {np.degrees(c['residual_rms']['gyro'][0]):.2f} ->"
          f" {np.degrees(c['residual_rms']['gyro'][1]):.2f} deg/s (motion)\n")  # fmt: skip
    j, jm = c["jitter_s"], c["jitter_s_moments"]
    print("jitter sigma_t fitted on " + train + ": " + ", ".join(
        f"{s} {1e3 * j[s]:.3f} ms (moments {1e3 * jm.get(s, 0.0):.3f} ms)" for s in j) + "\n")  # fmt: skip
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
    if "injection" not in fig:
        return
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
    price = fig["jitter_price"]
    print("\nglt smallest detectable step (50 % per-sample detection, alpha = 1 %), typical"
          " sensor, at rest and in the motion phase (median / 90th percentile widening):\n")  # fmt: skip
    print("| type | at rest | motion, median | motion, 90th pct | injected in motion: amplitude,"
          " glt MAR % |\n|---|---|---|---|---|")  # fmt: skip
    for s, unit, k in (("gyro", "deg/s", np.degrees(1.0)), ("accel", "m/s^2", 1.0)):
        if s not in price:
            continue
        v = price[s]
        print(f"| {s} | {k * v['rest_median']:.3g} {unit} | {k * v['motion_median']:.3g} {unit}"
              f" ({v['motion_median_widening']:.0f}x) | {k * v['motion_p90']:.3g} {unit}"
              f" ({v['motion_p90_widening']:.0f}x) | {k * v['injected_amplitude']:.3g} {unit}"
              f" on {v['sensor']}: {pct(v.get('injected_mar'))} |")  # fmt: skip


if __name__ == "__main__":
    main()
