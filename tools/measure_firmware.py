"""px4-selector and ap-consistency on paper-table4: out-of-sample FAR and step detection.

Per seed: a 20 s paper-table4 log; FAR counts alarms on the samples after the 2 s
calibration window of the fault-free log; then a step on imu0.gyro.x at 10 s of each
amplitude: MAR (missed fault samples), decision-time delay (these detectors are causal: the
first alarm on a fault sample minus the onset) and FIR (alarms on fault samples isolating
another sensor). Defaults are the firmware's parameters.

Run: PYTHONPATH=$PWD python tools/measure_firmware.py --seeds 7000:7020
"""

from __future__ import annotations

import argparse
from typing import Any

import numpy as np

from imufdi_cli.detectors import make_detector
from imufdi_cli.faults import FaultInjector, active_mask, parse_fault_spec
from imufdi_cli.simulate import preset, simulate_block

AMPLITUDES = (0.9, 10.0, 30.0)  # deg/s
CONFIGS: dict[str, tuple[str, dict[str, Any]]] = {
    "px4-selector": ("px4-selector", {"types": "gyro"}),
    "ap-consistency": ("ap-consistency", {"types": "gyro"}),
    "ap-consistency hold=1s": ("ap-consistency", {"types": "gyro", "hold": "1s"}),
}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", default="7000:7020", help="START:STOP")
    args = parser.parse_args()
    lo, hi = (int(v) for v in args.seeds.split(":"))
    stats: dict[tuple[str, str], list[float]] = {}
    for seed in range(lo, hi):
        array, clean = simulate_block(preset("paper-table4", seed=seed, duration="20s"))
        ncal = int(2.0 * array.rate_hz)
        t0 = int(clean.t_ns[0])
        for label, (name, params) in CONFIGS.items():
            det = make_detector(name, params)
            det.fit(clean.slice(0, ncal), array)
            free = det.process(clean)["gyro"]
            stats.setdefault((label, "far"), []).append(float(free.alarm[ncal:].mean()))
            for amp in AMPLITUDES:
                spec = f"step:imu0.gyro.x,at=10s,amp={amp}deg/s"
                injector = FaultInjector(
                    [parse_fault_spec(spec, array)], array, seed=seed, t0_ns=t0
                )
                faulty = injector.apply_block(clean)
                truth = active_mask(injector.faults, array.sensor_ids("gyro"), faulty.t_ns, t0)
                rows = truth.any(axis=1)
                onset = int(np.flatnonzero(rows)[0])
                det = make_detector(name, params)
                det.fit(clean.slice(0, ncal), array)
                out = det.process(faulty)["gyro"]
                hits = np.flatnonzero(out.alarm & rows)
                delay = (hits[0] - onset) / array.rate_hz if hits.size else np.nan
                wrong = out.isolated[out.alarm & rows] != 0
                stats.setdefault((label, f"mar{amp}"), []).append(float(np.mean(~out.alarm[rows])))
                stats.setdefault((label, f"delay{amp}"), []).append(float(delay))
                stats.setdefault((label, f"fir{amp}"), []).append(
                    float(wrong.mean()) if wrong.size else np.nan
                )
    print(f"paper-table4 (with outliers), gyro, seeds {lo}-{hi - 1}; step on imu0.gyro.x at 10 s")
    header = " | ".join(f"{a:g} deg/s: MAR %, delay s, FIR %" for a in AMPLITUDES)
    print(f"| detector | FAR % (mean, worst) | {header} |")
    print("|---|---|" + "---|" * len(AMPLITUDES))
    for label in CONFIGS:
        far = np.array(stats[(label, "far")])
        cells = []
        for amp in AMPLITUDES:
            mar = 100 * np.mean(stats[(label, f"mar{amp}")])
            delays = np.array(stats[(label, f"delay{amp}")])
            delay = "never" if np.all(np.isnan(delays)) else f"{np.nanmean(delays):.2f}"
            firs = np.array(stats[(label, f"fir{amp}")])
            fir = "—" if np.all(np.isnan(firs)) else f"{100 * np.nanmean(firs):.1f}"
            cells.append(f"{mar:.1f}, {delay}, {fir}")
        print(
            f"| {label} | {100 * far.mean():.2f} ({100 * far.max():.2f}) | "
            + " | ".join(cells)
            + " |"
        )


if __name__ == "__main__":
    main()
