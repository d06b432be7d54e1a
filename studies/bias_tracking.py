"""Slow bias tracking (``track_bias``) against slow drift faults (docs/real-arrays.md).

Tracking removes slow parity offsets, so a drift fault slow enough is tracked too. This
measures, for tracking time constants ``tau`` (0 = off), the detection delay and MAR of
pca-parity and glt on gyro drift faults of several rates, on simulated static 8-IMU logs
with the MIMU4444 noise (gyro 0.19 deg/s, accel 0.044 m/s^2, 62.5 Hz, 300 s), a drift
from 60 s to the end on imu2.gyro.y, ``--calibrate 0s:10s``. Evaluation seeds 1..N (nothing
was tuned on them; the real-data FAR side of the trade-off is in real_arrays.py)::

    python studies/bias_tracking.py --out /tmp/tracking [--seeds 3]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from imufdi_cli.detect import detect_file  # noqa: E402
from imufdi_cli.faults import inject_file  # noqa: E402
from imufdi_cli.pipeline import simulate_file  # noqa: E402
from imufdi_cli.report import build_report  # noqa: E402

RATES_DEG_S2 = (0.001, 0.003, 0.01, 0.03)
TAUS_S = (0.0, 60.0, 300.0)
DETECTORS = ("glt", "pca-parity")
OPTIONS = {
    "imus": 8,
    "rate": "62.5Hz",
    "duration": "300s",
    "motion": "static",
    "gyro_noise": "0.19deg/s",
    "accel_noise": "0.044m/s^2",
    "outliers": False,
}


def run(out: Path, seeds: int) -> dict[str, Any]:
    results: dict[str, Any] = {}
    for seed in range(1, seeds + 1):
        log = out / f"sim-{seed}.mcap"
        simulate_file(None, str(log), seed=seed, options=OPTIONS)
        for tau in TAUS_S:
            params = {"track_bias": f"{tau}s"}
            clean = out / f"clean-{seed}-{tau:g}.mcap"
            detect_file(str(log), str(clean), [(d, params) for d in DETECTORS],
                        calibrate=(0.0, 10.0))  # fmt: skip
            for entry in build_report(str(clean), window=(10.0, None)).entries:
                key = f"{entry.detector}.{entry.sensor_type}.tau={tau:g}.far"
                results.setdefault(key, []).append(entry.metrics.alarm_rate)
            for rate in RATES_DEG_S2:
                faulty = out / f"drift-{seed}-{rate:g}.mcap"
                if not faulty.exists():
                    spec = f"drift:imu2.gyro.y,at=60s,rate={rate}deg/s^2"
                    inject_file(str(log), str(faulty), [spec], [], seed=seed)
                detected = out / f"drift-{seed}-{rate:g}-{tau:g}.mcap"
                detect_file(str(faulty), str(detected), [(d, params) for d in DETECTORS],
                            calibrate=(0.0, 10.0))  # fmt: skip
                for entry in build_report(str(detected), window=(10.0, None)).entries:
                    if entry.sensor_type != "gyro":
                        continue
                    m = entry.metrics
                    key = f"{entry.detector}.gyro.tau={tau:g}.rate={rate:g}"
                    results.setdefault(key + ".mar", []).append(m.mar)
                    results.setdefault(key + ".delay", []).append(m.detection_delay_s)
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--seeds", type=int, default=3)
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    results = run(args.out, args.seeds)
    (args.out / "tracking.json").write_text(json.dumps(results, indent=2))
    print(f"gyro drift on imu2.gyro.y from 60 s, static 8-IMU logs, seeds 1..{args.seeds}:"
          " mean MAR % / mean detection delay s (undetected runs: delay counted as missing)\n")  # fmt: skip
    header = "| detector | tau s | FAR % (no fault) | " + " | ".join(
        f"{r:g} deg/s^2" for r in RATES_DEG_S2
    )
    print(header + " |\n|" + "---|" * (3 + len(RATES_DEG_S2)))
    for det in DETECTORS:
        for tau in TAUS_S:
            far = 100 * np.mean(results[f"{det}.gyro.tau={tau:g}.far"])
            cells = []
            for rate in RATES_DEG_S2:
                key = f"{det}.gyro.tau={tau:g}.rate={rate:g}"
                mar = [v for v in results[key + ".mar"] if v is not None]
                delays = [v for v in results[key + ".delay"] if v is not None]
                delay = f"{np.mean(delays):.1f}" if delays else "never"
                cells.append(f"{100 * np.mean(mar):.1f} / {delay}")
            print(f"| {det} | {tau:g} | {far:.2f} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
