"""Figures of the noise-glr and pca-parity detectors on the reference scenarios, and speed.

Run: ``python studies/noise_glr.py [--seeds 20] [--first-seed 7000] [--part ...]``;
``--part levels`` gives noise-glr's fault-free levels and its bias-fault rows,
``--part noise`` its power against noise growth, ``--part real --train A.mcap --test B.mcap``
its levels and power on two MIMU4444 recordings (ingested by studies/real_arrays.py),
with and without the healthy noise spread that ``calibrate`` learns on ``--train``.
Prints the tables quoted in docs/algorithms/noise-glr.md and docs/algorithms/pca-parity.md.
Means over seeds; "worst" is the worst seed.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

from imufdi_cli.array import ArrayConfig
from imufdi_cli.detectors.base import DetectionBlock, parse_params
from imufdi_cli.detectors.glt import GltDetector
from imufdi_cli.detectors.noise_glr import NoiseGlrDetector, leave_one_out_operator
from imufdi_cli.detectors.pca_parity import PcaParityDetector
from imufdi_cli.errors import ImufdiError
from imufdi_cli.faults import FaultInjector, parse_fault_spec
from imufdi_cli.log import ImuBlock, iter_blocks
from imufdi_cli.simulate import preset, simulate_block


def make_log(name: str, seed: int, specs: tuple[str, ...] = (), **overrides: object):
    array, block = simulate_block(preset(name, seed=seed, **overrides))
    faults = [parse_fault_spec(s, array) for s in specs]
    if faults:
        block = FaultInjector(faults, array, seed=seed, t0_ns=int(block.t_ns[0])).apply_block(block)
    return array, block


def run(cls, params, array: ArrayConfig, block: ImuBlock, calibrate=(0.0, 2.0), block_size=4096):
    detector = cls(**parse_params(cls.PARAMS, params, cls.name))
    t = block.t_s()
    detector.fit(block.mask((t >= calibrate[0]) & (t < calibrate[1])), array)
    outputs = [detector.process(b) for b in iter_blocks(block, block_size)]
    return {s: DetectionBlock.concatenate([o[s] for o in outputs]) for s in outputs[0]}


def event_figures(out: DetectionBlock, t: np.ndarray, start: float, end: float, sensor: int):
    """FAR (after the 0-2 s calibration window), delay, rate after 1st detection, recovery,
    isolation, 1 - MAR."""
    alarm = out.alarm
    fault = (t >= start) & (t < end)
    far = float(alarm[~fault & (t >= 2.0)].mean())
    hits = np.flatnonzero(alarm & fault)
    if hits.size == 0:
        return far, np.nan, 0.0, np.nan, np.nan, 0.0
    delay = float(t[hits[0]] - start)
    rate = float(alarm[hits[0] : np.flatnonzero(fault)[-1] + 1].mean())
    # recovery: until alarms stop for good (the last alarm within 2 s after the end)
    late = np.flatnonzero(alarm & (t >= end) & (t < end + 2.0))
    recovery = float(t[late[-1]] - end + (t[1] - t[0])) if late.size else 0.0
    isolation = float((out.isolated[alarm & fault] == sensor).mean())
    return far, delay, rate, recovery, isolation, float(alarm[fault].mean())


def noise_part(seeds: range) -> None:
    spec = "noise:imu0.accel.x,at=12s,until=18s,factor={}"
    print("## noise-glr on wearable12, noise x3 on imu0.accel.x 12-18 s, calibration 0-2 s")
    print(
        "detector | FAR | delay s (worst) | rate after 1st det | recovery s (worst) | iso | 1-MAR"
    )
    for label, cls, params in (
        ("noise-glr defaults", NoiseGlrDetector, {}),
        ("noise-glr level_confidence=0 (F)", NoiseGlrDetector, {"level_confidence": 0.0}),
        ("noise-glr level_confidence=0.99", NoiseGlrDetector, {"level_confidence": 0.99}),
        ("noise-glr release=0", NoiseGlrDetector, {"release": 0.0}),
        ("noise-glr a=0.01", NoiseGlrDetector, {"alpha": 0.01}),
        ("noise-glr lever_arm=false", NoiseGlrDetector, {"lever_arm": False}),
        ("glt (default)", GltDetector, {}),
    ):
        rows = []
        try:
            for seed in seeds:
                array, block = make_log("wearable12", seed, (spec.format(3),))
                out = run(cls, params, array, block)["accel"]
                rows.append(event_figures(out, block.t_s(), 12.0, 18.0, 0))
        except ImufdiError as err:
            print(f"{label} | failed: {err}")
            continue
        r = np.array(rows)
        print(
            f"{label} | {np.nanmean(r[:, 0]):.4f} (worst {np.nanmax(r[:, 0]):.4f}) | "
            f"{np.nanmean(r[:, 1]):.3f} ({np.nanmax(r[:, 1]):.2f}) | {np.nanmean(r[:, 2]):.4f} "
            f"(min {np.nanmin(r[:, 2]):.4f}) | {np.nanmean(r[:, 3]):.3f} ({np.nanmax(r[:, 3]):.2f})"
            f" | {np.nanmean(r[:, 4]):.4f} | {np.nanmean(r[:, 5]):.4f} (min {np.nanmin(r[:, 5]):.4f})"
        )
    print("\n## detection delay against the noise factor (noise-glr defaults, mean / worst)")
    for factor in (1.5, 2.0, 3.0, 5.0):
        rows = []
        for seed in seeds:
            array, block = make_log("wearable12", seed, (spec.format(factor),))
            out = run(NoiseGlrDetector, {}, array, block)["accel"]
            rows.append(event_figures(out, block.t_s(), 12.0, 18.0, 0))
        r = np.array(rows)
        print(
            f"factor {factor}: delay {np.nanmean(r[:, 1]):.3f} s (worst {np.nanmax(r[:, 1]):.2f}),"
            f" rate {np.nanmean(r[:, 2]):.3f}, recovery {np.nanmean(r[:, 3]):.3f} s,"
            f" iso {np.nanmean(r[:, 4]):.3f}, 1-MAR {np.nanmean(r[:, 5]):.3f},"
            f" FAR {np.nanmean(r[:, 0]):.4f}, detected {np.isfinite(r[:, 1]).sum()}/{len(seeds)}"
        )


#: Fault-free level cases: label, preset, options, calibration window (s).
LEVEL_CASES: tuple[tuple[str, str, dict, tuple[float, float]], ...] = (
    ("wearable12, 30 s", "wearable12", {}, (0.0, 2.0)),
    ("paper-table4 with its outliers, 20 s", "paper-table4", {"duration": 20.0}, (0.0, 2.0)),
    ("conical6, 20 s, calibration 0-5 s", "conical6", {"duration": 20.0}, (0.0, 5.0)),
    ("wearable12, 30 s, calibration 0-10 s", "wearable12", {}, (0.0, 10.0)),
    ("conical6, 30 s, calibration 0-10 s", "conical6", {"duration": 30.0}, (0.0, 10.0)),
    ("wearable12, 200 s", "wearable12", {"duration": 200.0}, (0.0, 2.0)),
    ("paper-table4 with its outliers, 200 s", "paper-table4", {"duration": 200.0}, (0.0, 2.0)),
    ("conical6, 200 s, calibration 0-5 s", "conical6", {"duration": 200.0}, (0.0, 5.0)),
)


def level_thresholds(params: dict, array: ArrayConfig, calibration: ImuBlock, n: int) -> dict:
    """Per-sample thresholds (n,) of each sensor type for ``params`` (the statistic does not
    depend on ``level_confidence``, only the threshold does)."""
    detector = NoiseGlrDetector(**parse_params(NoiseGlrDetector.PARAMS, params, "noise-glr"))
    detector.fit(calibration, array)
    fill = np.minimum(np.arange(n), detector.window_samples - 1)  # window fill - 1
    return {s: m.threshold[fill] for s, m in detector.models.items()}


def episodes(alarm: np.ndarray) -> int:
    """Alarm episodes (rising edges)."""
    return int(np.count_nonzero(np.diff(alarm.astype(np.int8), prepend=0) == 1))


def levels_part(seeds: range, long_seeds: range, confidences: tuple[float, ...]) -> None:
    """Fault-free out-of-sample FAR per preset and sensor type, for several
    ``level_confidence`` values (one detector pass per log; thresholds differ)."""
    alpha = 0.001
    print(f"\n## noise-glr fault-free levels, alpha = {alpha}; FAR after the calibration window")
    print("case | type | level_confidence | mean/alpha | worst seed/alpha | seeds > 4 alpha |"
          " episodes (seeds) | threshold on the variance ratio")  # fmt: skip
    for label, name, options, calibrate in LEVEL_CASES:
        use = long_seeds if options.get("duration", 0.0) >= 100.0 else seeds
        rows: dict[tuple[str, float], list] = {}
        for seed in use:
            array, block = make_log(name, seed, **options)
            t = block.t_s()
            calibration = block.mask((t >= calibrate[0]) & (t < calibrate[1]))
            out = run(NoiseGlrDetector, {}, array, block, calibrate)
            after = t >= calibrate[1]
            for c in confidences:
                thresholds = level_thresholds({"level_confidence": c}, array, calibration, len(t))
                for sensor_type, o in out.items():
                    alarm = (o.statistic > thresholds[sensor_type]) & after
                    rows.setdefault((sensor_type, c), []).append(
                        (alarm[after].mean() / alpha, episodes(alarm), thresholds[sensor_type][-1])
                    )
        for (sensor_type, c), values in rows.items():
            r = np.array(values)
            print(
                f"{label} | {sensor_type} | {c:g} | {r[:, 0].mean():.2f} | {r[:, 0].max():.2f} |"
                f" {int((r[:, 0] > 4).sum())} | {int(r[:, 1].sum())} ({int((r[:, 1] > 0).sum())})"
                f" | h = {r[0, 2]:.1f}"
            )


def bias_part(seeds: range) -> None:
    """Mean changes noise-glr must not call noise growth (paper-table4 without outliers)."""
    print("\n## bias faults on paper-table4 (outliers=False, 20 s): gyro noise alarms during the"
          " fault (1 - MAR), defaults")  # fmt: skip
    for label, spec, start in (
        ("0.9 deg/s step on imu0.gyro.x at 5 s", "step:imu0.gyro.x,at=5s,amp=0.9deg/s", 5.0),
        ("0.05 deg/s/min drift on imu5.gyro.z from 2 s", "drift:imu5.gyro.z,at=2s,rate=0.05deg/s/min", 2.0),
    ):  # fmt: skip
        rates = []
        for seed in seeds:
            array, block = make_log("paper-table4", seed, (spec,), outliers=False, duration=20.0)
            out = run(NoiseGlrDetector, {}, array, block)["gyro"]
            rates.append(out.alarm[block.t_s() >= max(start, 2.0)].mean())
        print(f"{label} | mean {np.mean(rates):.5f} | worst seed {np.max(rates):.5f}")


def pca_part(seeds: range) -> None:
    spec = ("step:imu5.gyro.z,at=6s,amp=0.5deg/s",)
    print("\n## pca-parity on conical6, 0.5 deg/s step on imu5.gyro.z at 6 s")
    print("params | calib | FAR calib end-6 s | runs with an alarm then | first alarm s | delay s")
    print("       |       | (worst) | | (mean) | (worst) | isolation | amplitude deg/s")
    cases = (
        ({}, (0.0, 2.0)),
        ({}, (0.0, 5.0)),
        ({"alpha": 0.001}, (0.0, 5.0)),
        ({"leak": "none"}, (0.0, 5.0)),
        ({}, (0.0, 1.0)),
        ({"space": "raw"}, (0.0, 1.0)),
        ({"space": "raw"}, (0.0, 2.0)),
    )
    for params, calibrate in cases:
        rows = []
        for seed in seeds:
            array, block = make_log("conical6", seed, spec)
            t = block.t_s()
            out = run(PcaParityDetector, params, array, block, calibrate)["gyro"]
            before = (t < 6.0) & (t >= calibrate[1])  # out of sample, before the fault
            first = t[np.flatnonzero(out.alarm)[0]] if out.alarm.any() else np.nan
            hits = np.flatnonzero(out.alarm & (t >= 6.0))
            delay = t[hits[0]] - 6.0 if hits.size else np.nan
            isolation = (out.isolated[hits] == 5).mean() if hits.size else np.nan
            amplitude = np.nanmedian(np.rad2deg(out.amplitude[hits])) if hits.size else np.nan
            rows.append(
                (
                    out.alarm[before].mean(),
                    out.alarm[before].any(),
                    first,
                    delay,
                    isolation,
                    amplitude,
                )
            )
        r = np.array(rows, dtype=float)
        print(
            f"{params or 'default'} | {calibrate[0]:g}-{calibrate[1]:g} s | "
            f"{np.nanmean(r[:, 0]):.4f} ({np.nanmax(r[:, 0]):.4f}) | {int(r[:, 1].sum())}/{len(seeds)} | "
            f"{np.nanmean(r[:, 2]):.2f} | {np.nanmean(r[:, 3]):.3f} ({np.nanmax(r[:, 3]):.2f}) | "
            f"{np.nanmean(r[:, 4]):.3f} | {np.nanmean(r[:, 5]):.3f}"
        )
    print(
        "\n## chip-to-chip biases 0.5 deg/s and 0.05 m/s^2, no fault (paper-table4 without outliers)"
    )
    print("detector | gyro FAR (worst) | accel FAR (worst)")
    for label, cls, params in (
        ("pca-parity", PcaParityDetector, {}),
        ("glt bias=true", GltDetector, {}),
        ("glt bias=false (plain)", GltDetector, {"bias": False}),
    ):
        rows = []
        for seed in seeds:
            array, block = make_log(
                "paper-table4",
                seed,
                outliers=False,
                duration=20.0,
                chip_biases={"gyro": "0.5deg/s", "accel": "0.05m/s^2"},
            )
            out = run(cls, params, array, block)
            after = block.t_s() >= 2.0
            rows.append((out["gyro"].alarm[after].mean(), out["accel"].alarm[after].mean()))
        r = np.array(rows)
        print(
            f"{label} | {r[:, 0].mean():.4f} ({r[:, 0].max():.4f}) | "
            f"{r[:, 1].mean():.4f} ({r[:, 1].max():.4f})"
        )


def speed_part() -> None:
    """Leave-one-out residuals: PRESS operator vs one least-squares fit per left-out sensor."""
    array, block = make_log("wearable12", 0)
    H = array.measurement_matrix("accel")
    m = array.select(block.accel, "accel")
    repeats = 5
    start = time.perf_counter()
    for _ in range(repeats):
        operator, _ = leave_one_out_operator(H)
        fast = m @ operator.T
    fast_s = (time.perf_counter() - start) / repeats
    start = time.perf_counter()
    for _ in range(repeats):
        slow = np.empty_like(m)
        for j in range(H.shape[0]):
            keep = np.arange(H.shape[0]) != j
            x, *_ = np.linalg.lstsq(H[keep], m[:, keep].T, rcond=None)
            slow[:, j] = m[:, j] - H[j] @ x
    slow_s = (time.perf_counter() - start) / repeats
    print("\n## speed: leave-one-out residuals of 36 accelerometers, 3000 samples")
    print(f"PRESS operator {fast_s * 1e3:.2f} ms, per-sensor lstsq {slow_s * 1e3:.2f} ms, "
          f"ratio {slow_s / fast_s:.1f}x, max difference {np.abs(fast - slow).max():.2e}")  # fmt: skip
    detector = NoiseGlrDetector()
    t = block.t_s()
    detector.fit(block.mask(t < 2.0), array)
    start = time.perf_counter()
    for b in iter_blocks(block, 1000):
        detector.process(b)
    total = time.perf_counter() - start
    print(f"noise-glr process: {len(block) / total / 1e3:.0f} k samples/s (gyro + accel, 12 IMUs)")


#: Real recordings: bias calibration window of the test log (s) and injected fault length (s).
REAL_CALIBRATION = (0.0, 10.0)
REAL_FAULT_S = 10.0


def _real_alarms(array: ArrayConfig, block: ImuBlock, params: dict) -> dict[str, DetectionBlock]:
    return run(NoiseGlrDetector, params, array, block, calibrate=REAL_CALIBRATION)


def real_part(train: str, test: str, seed: int, factor: float) -> None:
    """Per-orientation alarm rates and injected noise growth on two MIMU4444 recordings.

    ``calibrate`` on ``train`` gives the chip calibration, noise levels and noise spread;
    ``test`` is calibrated with it and noise-glr fitted on its first 10 s. Fault-free:
    alarm rate per static orientation of ``test`` (after 10 s) and in its motion phase
    (clipped rows not scored). Injected: in the middle of every static orientation, for
    10 s, white noise added to one gyro and one accelerometer axis (a different one each
    time) so that its sigma becomes ``factor`` times its own sigma in that orientation
    (``std(diff)/sqrt(2)`` of the interval); 1 - MAR = share of those samples alarmed,
    and the share isolated to the faulty sensor. ``seed`` draws the added noise.
    """
    from imufdi_cli.calibrate import calibrate_file, find_static
    from imufdi_cli.mcapio import read_array
    from imufdi_cli.validity import apply_calibration, flag_values

    base = ArrayConfig.load(
        Path(__file__).resolve().parents[1] / "imufdi_cli/sample_logs/mimu4444-array.toml"
    )
    result = calibrate_file(train, base=base)
    cal = result.array
    log_array, raw = read_array(test)
    t = raw.t_s()
    intervals, _ = find_static(log_array, raw.accel, raw.gyro, t, np.ones(len(t), bool))
    motion_start = float(intervals[-1].end_s) + 2.0
    clipped = np.zeros(len(t), dtype=bool)
    for s in ("gyro", "accel"):
        c, i = flag_values(raw.get(s), s, cal.range.get(s))
        clipped |= (c | i).any(axis=(1, 2))
    block = apply_calibration(raw, cal)
    without = cal.with_noise_spread([{} for _ in range(cal.n_imus)])
    print(f"## noise-glr on {Path(test).parent.name}/{Path(test).name}, calibrated on {train}"
          f" ({result.orientations} orientations), --calibrate 0s:10s, defaults"
          f" (alpha 0.1 %); load {os.getloadavg()[0]:.1f}")  # fmt: skip
    for s in ("gyro", "accel"):
        kappa = cal.sensor_noise_spread(s)
        if kappa is not None:
            ids = cal.sensor_ids(s)
            top = np.argsort(kappa)[::-1][:5]
            print(f"{s} noise spread kappa: median {np.median(kappa):.2f}, largest "
                  + ", ".join(f"{ids[j]} {kappa[j]:.2f}" for j in top))  # fmt: skip
    windows = [(max(i.start_s, REAL_CALIBRATION[1]), i.end_s) for i in intervals]
    print("\narray | type | static mean % | worst orientation % | orientations > 4 alpha |"
          " motion % (clipped rows not scored)")  # fmt: skip
    for label, array in (("without spread", without), ("with spread", cal)):
        out = _real_alarms(array, block, {})
        for s, det in out.items():
            rates = [det.alarm[(t >= a) & (t <= b)].mean() for a, b in windows if b > a]
            motion = det.alarm[(t >= motion_start) & ~clipped].mean()
            print(f"{label} | {s} | {100 * np.mean(rates):.2f} | {100 * np.max(rates):.2f} |"
                  f" {sum(r > 0.004 for r in rates)}/{len(rates)} | {100 * motion:.1f}")  # fmt: skip
    rng = np.random.default_rng(seed)
    faulty = {s: np.array(block.get(s), copy=True) for s in ("gyro", "accel")}
    truth: dict[str, list[tuple[np.ndarray, int]]] = {"gyro": [], "accel": []}
    for n, item in enumerate(intervals):
        mid = 0.5 * (max(item.start_s, REAL_CALIBRATION[1]) + item.end_s)
        rows = (t >= mid - REAL_FAULT_S / 2) & (t < mid + REAL_FAULT_S / 2)
        if item.end_s - item.start_s < REAL_FAULT_S + 2 or mid - REAL_FAULT_S / 2 < 12.0:
            continue
        for s, stride in (("gyro", 7), ("accel", 5)):
            imu_idx, axis_idx = cal.sensor_index(s)
            j = (n * stride) % len(imu_idx)
            k, a = int(imu_idx[j]), int(axis_idx[j])
            sigma0 = float(np.std(np.diff(faulty[s][rows, k, a])) / np.sqrt(2.0))
            added = sigma0 * np.sqrt(factor**2 - 1.0)
            faulty[s][rows, k, a] += added * rng.standard_normal(int(rows.sum()))
            truth[s].append((rows, j))
    injected = ImuBlock(t_ns=block.t_ns, gyro=faulty["gyro"], accel=faulty["accel"])
    print(f"\ninjected noise x{factor:g} on one axis for {REAL_FAULT_S:g} s in each orientation"
          f" (seed {seed})\narray | type | faults | 1-MAR % (worst fault) | isolated to the faulty"
          " sensor % of alarms")  # fmt: skip
    for label, array in (("without spread", without), ("with spread", cal)):
        out = _real_alarms(array, injected, {})
        for s, det in out.items():
            hits = [det.alarm[rows].mean() for rows, _ in truth[s]]
            iso = [np.mean(det.isolated[rows][det.alarm[rows]] == j) for rows, j in truth[s]
                   if det.alarm[rows].any()]  # fmt: skip
            weakest = cal.sensor_ids(s)[truth[s][int(np.argmin(hits))][1]]
            print(f"{label} | {s} | {len(hits)} | {100 * np.mean(hits):.1f}"
                  f" ({100 * np.min(hits):.1f}, {weakest}) | {100 * np.mean(iso):.1f}")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seeds", type=int, default=20, help="number of seeds")
    parser.add_argument("--first-seed", type=int, default=7000, help="evaluation seeds start")
    parser.add_argument(
        "--part", choices=("all", "noise", "levels", "pca", "speed", "real"), default="all"
    )
    parser.add_argument(
        "--long-first-seed",
        type=int,
        default=None,
        help="seeds of the 200 s logs (default: --first-seed)",
    )
    parser.add_argument(
        "--confidences",
        default="0.95",
        help="level_confidence values for --part levels (comma-separated)",
    )
    parser.add_argument("--train", help="--part real: calibration recording (ingested MCAP)")
    parser.add_argument("--test", help="--part real: test recording (ingested MCAP)")
    parser.add_argument("--factor", type=float, default=3.0, help="--part real: noise factor")
    args = parser.parse_args()
    if args.part == "real":
        if not (args.train and args.test):
            parser.error("--part real needs --train and --test")
        real_part(args.train, args.test, args.first_seed, args.factor)
        return
    if args.part in ("all", "levels"):
        first_long = args.first_seed if args.long_first_seed is None else args.long_first_seed
        levels_part(
            range(args.first_seed, args.first_seed + args.seeds),
            range(first_long, first_long + args.seeds),
            tuple(float(c) for c in args.confidences.split(",")),
        )
        bias_part(range(args.first_seed, args.first_seed + args.seeds))
    if args.part in ("all", "noise"):
        noise_part(range(args.first_seed, args.first_seed + args.seeds))
    if args.part in ("all", "pca"):
        pca_part(range(args.first_seed, args.first_seed + args.seeds))
    if args.part in ("all", "speed"):
        speed_part()


if __name__ == "__main__":
    main()
