"""Detectors under a false-alarm budget: fault-free episodes per hour on long simulated
logs, and the delays of three reference faults against Lorden's references.

Parts (``--part``):

- ``levels``: per detector, preset and status channel, the false alarm episodes of
  fault-free logs of ``--hours`` per seed (calibrated on the first 2 s, streamed in blocks
  of 4096 samples), the tested hours, the rate and its 95 % Poisson upper bound, and the
  same pooled over the presets per channel;
- ``delays``: on paper-table4 at the budget, a 0.9 deg/s and a 0.3 deg/s step and a
  1 deg/s^2 drift on imu3.gyro.y with an onset drawn uniformly in [30, 30.5] s per seed:
  delay from the onset to the decision time of the first alarm (a detector's look-ahead
  counted), share of alarm rows isolating the faulty sensor, and Lorden's reference (the
  optimal test's delay at the same rate for glt's whitened parity evidence,
  :func:`imufdi_cli.maths.sequential.lorden_delay_samples` and ``lorden_drift_samples``)
  with the ratio.

Example (the figures of docs/algorithms/{pca-parity,bank,woa-mvmd-glt}.md)::

    PYTHONPATH=. python studies/budget.py --part levels --seeds 33011:33015 --hours 1 \\
        --detectors glt,pca-parity,bank
    PYTHONPATH=. python studies/budget.py --part levels --seeds 33011:33013 --hours 1 \\
        --detectors woa-mvmd-glt
    PYTHONPATH=. python studies/budget.py --part delays --seeds 33030:33050
"""

from __future__ import annotations

import argparse
import math
import sys
from concurrent.futures import ProcessPoolExecutor
from typing import Any

import numpy as np

PRESETS = {
    "glt": ("paper-table4", "conical6", "wearable12"),
    "pca-parity": ("paper-table4", "conical6", "wearable12"),
    "bank": ("paper-table4", "conical6", "wearable12", "quadrotor-marg"),
    "woa-mvmd-glt": ("paper-table4", "conical6", "wearable12"),
}
FAULTS = (
    ("step 0.9 deg/s", "step:imu3.gyro.y,at={onset}s,amp=0.9deg/s"),
    ("step 0.3 deg/s", "step:imu3.gyro.y,at={onset}s,amp=0.3deg/s"),
    ("drift 1 deg/s^2", "drift:imu3.gyro.y,at={onset}s,rate=1deg/s^2"),
)


def _seeds(text: str) -> list[int]:
    start, _, stop = text.partition(":")
    return list(range(int(start), int(stop))) if stop else [int(start)]


def _level_job(job: tuple[str, str, float, int, float]) -> tuple[str, str, int, dict, float]:
    from imufdi_cli.detectors import make_detector
    from imufdi_cli.simulate import config_from_options, simulate

    detector_name, preset_name, hours, seed, budget = job
    config = config_from_options(preset_name, seed=seed, duration=f"{hours * 3600.0}s")
    array, blocks = simulate(config, block_size=4096)
    detector = make_detector(detector_name, {"false_alarms": budget / 3600.0})
    need = round(2.0 * array.rate_hz)
    last: dict[str, bool] = {}
    counts: dict[str, int] = {}
    tested = 0

    def count(outputs: dict) -> None:
        for sensor_type, out in outputs.items():
            alarm = np.asarray(out.alarm, bool)
            before = np.concatenate([[last.get(sensor_type, False)], alarm[:-1]])
            counts[sensor_type] = counts.get(sensor_type, 0) + int(np.sum(alarm & ~before))
            if alarm.size:
                last[sensor_type] = bool(alarm[-1])

    for index, block in enumerate(blocks):
        if index == 0:
            detector.fit(block.slice(0, need), array)
            block = block.slice(need, len(block))
        count(detector.process(block))
        tested += len(block)
    count(detector.flush())
    return detector_name, preset_name, seed, counts, tested / array.rate_hz / 3600.0


def poisson_upper(events: int, hours: float, level: float = 0.95) -> float:
    """Garwood's one-sided upper bound of a Poisson rate per hour."""
    from imufdi_cli.maths.quantiles import chi2

    return float(chi2.ppf(level, 2 * events + 2)) / 2.0 / hours


def levels(args: argparse.Namespace) -> None:
    jobs = [
        (name, preset_name, args.hours, seed, args.budget)
        for name in args.detectors
        for preset_name in PRESETS[name]
        if args.presets is None or preset_name in args.presets
        for seed in args.seeds
    ]
    results: list[tuple[str, str, int, dict, float]] = []
    with ProcessPoolExecutor(args.jobs) as pool:
        for result in pool.map(_level_job, jobs):
            print(
                f"# {result[0]} {result[1]} seed {result[2]}: {result[3]} in {result[4]:.2f} h",
                file=sys.stderr,
                flush=True,
            )
            results.append(result)
    print(
        f"False alarm episodes at a budget of {args.budget:g}/h, seeds {args.seeds[0]}-"
        f"{args.seeds[-1]}, {args.hours:g} h each\n"
    )
    print("| detector | preset | channel | episodes | tested h | per h | 95 % upper |")
    print("|---|---|---|---|---|---|---|")
    pooled: dict[tuple[str, str], list[float]] = {}
    for name in args.detectors:
        for preset_name in PRESETS[name]:
            rows = [r for r in results if r[0] == name and r[1] == preset_name]
            if not rows:
                continue
            for channel in sorted({c for r in rows for c in r[3]}):
                events = sum(r[3].get(channel, 0) for r in rows)
                hours = sum(r[4] for r in rows)
                pooled.setdefault((name, channel), [0, 0.0])
                pooled[(name, channel)][0] += events
                pooled[(name, channel)][1] += hours
                print(
                    f"| {name} | {preset_name} | {channel} | {events} | {hours:.1f} |"
                    f" {events / hours:.2f} | {poisson_upper(events, hours):.2f} |"
                )
    print("\nPooled over the presets:\n")
    print("| detector | channel | episodes | tested h | per h | 95 % upper |")
    print("|---|---|---|---|---|---|")
    for (name, channel), (events, hours) in pooled.items():
        print(
            f"| {name} | {channel} | {int(events)} | {hours:.1f} | {events / hours:.2f} |"
            f" {poisson_upper(int(events), hours):.2f} |"
        )


def _delay_job(job: tuple[str, str, str, int, float]) -> dict[str, Any]:
    from imufdi_cli.detectors import make_detector
    from imufdi_cli.faults import FaultInjector, parse_fault_spec
    from imufdi_cli.simulate import preset, simulate_block

    detector_name, label, template, seed, budget = job
    onset = 30.0 + np.random.default_rng(seed).uniform(0.0, 0.5)
    array, block = simulate_block(preset("paper-table4", seed=seed, duration=40.0))
    fault = parse_fault_spec(template.format(onset=f"{onset:.4f}"), array)
    block = FaultInjector([fault], array, seed=seed, t0_ns=int(block.t_ns[0])).apply_block(block)
    detector = make_detector(detector_name, {"false_alarms": budget / 3600.0})
    start = 200
    detector.fit(block.slice(0, start), array)
    pieces = [detector.process(block.slice(i, i + 997)) for i in range(start, len(block), 997)]
    pieces.append(detector.flush())
    alarm = np.concatenate([p["gyro"].alarm for p in pieces])
    isolated = np.concatenate([p["gyro"].isolated for p in pieces])
    t = block.t_s()[start:]
    target = array.sensor_ids("gyro").index("imu3.gyro.y")
    rows = np.arange(start, len(block))
    if hasattr(detector, "decision_index"):  # look-ahead: each row's decision sample
        decided = detector.decision_index(rows, len(block)) - start
    else:
        decided = rows - start
    hits = np.flatnonzero(alarm & (t[decided] >= onset))
    pre = int(np.count_nonzero(alarm & (t[decided] < onset)))
    record = {"detector": detector_name, "fault": label, "seed": seed, "pre": pre}
    if hits.size:
        record["delay"] = float(t[decided[hits[0]]] - onset)
        after = alarm & (t >= onset)
        record["right"] = float(np.mean(isolated[after] == target)) if after.any() else math.nan
    else:
        record["delay"] = math.inf
        record["right"] = math.nan
    return record


def _reference(label: str, budget: float) -> float:
    """Lorden's reference delay, s, of a fault of the study on paper-table4 at the budget:
    glt's whitened parity evidence (sensitivity sqrt(P_ii) / sigma, sigma 0.15 deg/s,
    P_ii = 45/48), the 2 n sensor-and-sign hypotheses, average run length ``f_s / rate``
    samples."""
    from imufdi_cli.maths.sequential import lorden_delay_samples, lorden_drift_samples

    rate_hz, n = 100.0, 48
    sensitivity = math.sqrt(45.0 / 48.0) / math.radians(0.15)  # z per rad/s
    run_length = rate_hz * 3600.0 / budget
    hypotheses = 2 * n
    if label.startswith("drift"):
        slope = sensitivity * math.radians(1.0) / rate_hz  # z per sample per sample
        return lorden_drift_samples(slope, run_length, hypotheses) / rate_hz
    size = math.radians(0.9 if "0.9" in label else 0.3)
    return lorden_delay_samples((sensitivity * size) ** 2, run_length, hypotheses) / rate_hz


def delays(args: argparse.Namespace) -> None:
    jobs = [
        (name, label, template, seed, args.budget)
        for name in args.detectors
        for label, template in FAULTS
        for seed in args.seeds
    ]
    with ProcessPoolExecutor(args.jobs) as pool:
        records = list(pool.map(_delay_job, jobs))
    print(
        f"paper-table4 at {args.budget:g}/h, imu3.gyro.y, onset U(30, 30.5) s, seeds"
        f" {args.seeds[0]}-{args.seeds[-1]}; delay to the decision time (look-ahead counted)\n"
    )
    print(
        "| detector | fault | delay s, mean (max) | Lorden s | ratio (mean) | right sensor,"
        " mean (min) | missed | false before onset |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for name in args.detectors:
        for label, _ in FAULTS:
            rows = [r for r in records if r["detector"] == name and r["fault"] == label]
            found = [r for r in rows if math.isfinite(r["delay"])]
            reference = _reference(label, args.budget)
            if found:
                d = np.array([r["delay"] for r in found])
                right = np.array([r["right"] for r in found])
                print(
                    f"| {name} | {label} | {d.mean():.3f} ({d.max():.3f}) | {reference:.3f} |"
                    f" {d.mean() / reference:.1f} | {np.nanmean(right):.4f}"
                    f" ({np.nanmin(right):.4f}) | {len(rows) - len(found)} |"
                    f" {sum(r['pre'] for r in rows)} |"
                )
            else:
                print(f"| {name} | {label} | never | {reference:.3f} | - | - | {len(rows)} | - |")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--part", choices=("levels", "delays"), required=True)
    parser.add_argument("--seeds", type=_seeds, default=_seeds("33011:33015"))
    parser.add_argument("--hours", type=float, default=3.0, help="per seed (levels)")
    parser.add_argument("--budget", type=float, default=1.0, help="false episodes per hour")
    parser.add_argument(
        "--detectors",
        type=lambda s: s.split(","),
        default=["glt", "pca-parity", "bank", "woa-mvmd-glt"],
    )
    parser.add_argument("--presets", type=lambda s: s.split(","), default=None)
    parser.add_argument("--jobs", type=int, default=1)
    args = parser.parse_args(argv)
    levels(args) if args.part == "levels" else delays(args)


if __name__ == "__main__":
    main()
