"""cnn-map on wearable12: speed (training + detection against a 60 s budget and real time)
and the 20-seed comparison with noise-glr and GLT quoted in docs/algorithms/cnn-map.md.

Run: ``python studies/cnn_map.py [--seeds 20] [--part all|speed|table]``.
Fault ``noise:imu0.accel.x,at=12s,until=18s,factor=3``; calibration 0-10 s (cnn-map needs
more fault-free data than 2 s to train; noise-glr and GLT are run with 0-2 s and 0-10 s).

``--part mapping-level --first-seed 12000 --seeds 10``: the level the mapping test would
have alone at alpha on fault-free wearable12 logs (calibration 0-10 s), from the default
detector's ``mapping_report`` (the mapping test only reports), out of sample (10-30 s) and
over the calibration window, beside the detector's own alarm rate (the input test's).

``--part input-step --first-seed 12000 --seeds 5``: what an accelerometer bias step (on
imu5.accel.x at 15 s; sigma = 0.03 m/s^2) does to the input test, which compares each
residual with its 8-sample local mean (``mapping_test=off``: the default's alarms without
training a network).

``--part library``: CPU of the two library costs of a cnn-map fit against their former
implementations (kept here as the baseline, measured in the same run):
``cusum.cusum_threshold`` at the input test's wearable12 setting (W = 8, alpha = 0.001 over
36 channels) and ``Sequential.input_gradients`` on the default network (8 filters, kernel 5,
a batch of 2048 windows of 24 samples), with the results checked equal, bit for bit.
"""

from __future__ import annotations

import argparse
import math
import os
import time

import numpy as np

from imufdi_cli.detectors.base import DetectionBlock, parse_params
from imufdi_cli.detectors.cnn_map import INPUT_DESIGN, CnnMapDetector, MappingNetwork
from imufdi_cli.detectors.cusum import CusumDesign, cusum_threshold
from imufdi_cli.detectors.glt import GltDetector
from imufdi_cli.detectors.noise_glr import NoiseGlrDetector
from imufdi_cli.faults import FaultInjector, active_mask, parse_fault_spec
from imufdi_cli.log import iter_blocks
from imufdi_cli.metrics import FaultWindow, compute_metrics
from imufdi_cli.simulate import preset, simulate_block

SPEC = "noise:imu0.accel.x,at=12s,until=18s,factor=3"
BUDGET_S = 60.0


def make_log(seed: int):
    array, block = simulate_block(preset("wearable12", seed=seed))
    faults = [parse_fault_spec(SPEC, array)]
    t0 = int(block.t_ns[0])
    block = FaultInjector(faults, array, seed=seed, t0_ns=t0).apply_block(block)
    return array, block, faults, t0


def run(cls, params, array, block, calibrate, detector=None):
    if detector is None:
        detector = cls(**parse_params(cls.PARAMS, params, cls.name))
    t = block.t_s()
    detector.fit(block.mask((t >= calibrate[0]) & (t < calibrate[1])), array)
    outs = [detector.process(b) for b in iter_blocks(block, 250)]
    return DetectionBlock.concatenate([o["accel"] for o in outs])


def speed_part() -> None:
    array, block, _, _ = make_log(0)
    detector = CnnMapDetector()
    start = time.perf_counter()
    run(CnnMapDetector, {}, array, block, (0.0, 10.0), detector)
    elapsed = time.perf_counter() - start
    assert detector.mapping is not None
    training = detector.mapping.training
    duration = len(block) / array.rate_hz
    print("## speed: cnn-map training (0-10 s) + detection of the 30 s wearable12 log")
    print(
        f"{elapsed:.2f} s; {elapsed / BUDGET_S:.3f} of the {BUDGET_S:.0f} s budget; "
        f"{elapsed / duration:.3f} x real time ({duration:.0f} s of data)"
    )
    print(
        f"mapping: held-out MAE {training['mae_rad_s']:.3f} rad/s (training"
        f" {training['train_mae_rad_s']:.3f}; paper 0.1475), best epoch {training['best_epoch']}"
        f" of {training['epochs_run']}"
    )


def table_part(seeds: int) -> None:
    cases = (
        ("cnn-map", CnnMapDetector, {}, (0.0, 10.0)),
        ("noise-glr", NoiseGlrDetector, {}, (0.0, 2.0)),
        ("noise-glr", NoiseGlrDetector, {}, (0.0, 10.0)),
        ("glt", GltDetector, {}, (0.0, 2.0)),
    )
    print(f"\n## wearable12, {SPEC}, {seeds} seeds (mean; worst seed in brackets)")
    print(
        "| detector | calibration | FAR (after calibration) | detection rate after 1st "
        "detection | delay s | recovery s | FIR | seeds detected |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for label, cls, params, calibrate in cases:
        rows = []
        for seed in range(seeds):
            array, block, faults, t0 = make_log(seed)
            out = run(cls, params, array, block, calibrate)
            t = block.t_s()
            ids = array.sensor_ids("accel")
            truth = active_mask(faults, ids, block.t_ns, t0)
            keep = t >= calibrate[1]  # figures on the samples after the calibration window
            window = FaultWindow("f0", (0,), t0 + 12 * 10**9, t0 + 18 * 10**9)
            metrics = compute_metrics(
                block.t_ns[keep], out.alarm[keep], out.isolated[keep], truth[keep], [window]
            )
            fault = truth[:, 0]
            hits = np.flatnonzero(out.alarm & fault)
            rate = out.alarm[hits[0] : np.flatnonzero(fault)[-1] + 1].mean() if hits.size else 0.0
            rows.append(
                (
                    metrics.far,
                    rate,
                    np.nan if metrics.detection_delay_s is None else metrics.detection_delay_s,
                    np.nan if metrics.recovery_delay_s is None else metrics.recovery_delay_s,
                    np.nan if metrics.fir is None else metrics.fir,
                    hits.size > 0,
                )
            )
        r = np.array(rows, dtype=float)
        print(
            f"| {label} | {calibrate[0]:g}-{calibrate[1]:g} s | {np.nanmean(r[:, 0]):.4f} "
            f"({np.nanmax(r[:, 0]):.4f}) | {np.nanmean(r[:, 1]):.4f} ({np.nanmin(r[:, 1]):.4f}) | "
            f"{np.nanmean(r[:, 2]):.3f} ({np.nanmax(r[:, 2]):.2f}) | {np.nanmean(r[:, 3]):.3f} "
            f"({np.nanmax(r[:, 3]):.2f}) | {np.nanmean(r[:, 4]):.3f} | {int(r[:, 5].sum())}/{seeds} |"
        )


def mapping_level_part(first_seed: int, seeds: int) -> None:
    """Mapping test's over-threshold rate / alpha, out of sample and in-sample."""
    print("\n## mapping test alone at alpha (mapping_report), fault-free wearable12")
    print("| seed | mapping, 10-30 s / alpha | mapping, 0-10 s / alpha | detector alarms / alpha |")
    print("|---|---|---|---|")
    out_rates = []
    for seed in range(first_seed, first_seed + seeds):
        array, block = simulate_block(preset("wearable12", seed=seed))
        t = block.t_s()
        detector = CnnMapDetector()
        calibration = block.mask(t < 10.0)
        detector.fit(calibration, array)
        for part in iter_blocks(calibration, 4096):
            detector.process(part)
        report = detector.mapping_report
        over_in, samples_in = report.over, report.samples
        alarms = np.concatenate(
            [detector.process(b)["accel"].alarm for b in iter_blocks(block.mask(t >= 10.0), 4096)]
        )
        rate_out = (report.over - over_in) / (report.samples - samples_in) / detector.alpha
        out_rates.append(rate_out)
        print(
            f"| {seed} | {rate_out:.2f} | {over_in / samples_in / detector.alpha:.2f} |"
            f" {alarms.mean() / detector.alpha:.2f} |",
            flush=True,
        )
    print(f"| mean (worst) | {np.mean(out_rates):.2f} ({np.max(out_rates):.2f}) | | |")


def input_step_part(first_seed: int, seeds: int) -> None:
    """Alarms after accelerometer bias steps of 1-33 sigma (the input test alone)."""
    print("\n## input test after a bias step on imu5.accel.x at 15 s, wearable12")
    print(
        "| step | seeds alarmed | alarmed samples in 1 s, mean (max) | last alarm after step, s (max) | right axis |"
    )
    print("|---|---|---|---|---|")
    for amp in (0.03, 0.06, 0.1, 0.3, 1.0):
        rows = []
        for seed in range(first_seed, first_seed + seeds):
            array, block = simulate_block(preset("wearable12", seed=seed))
            spec = f"step:imu5.accel.x,at=15s,amp={amp}m/s^2"
            faults = [parse_fault_spec(spec, array)]
            block = FaultInjector(faults, array, seed=seed, t0_ns=int(block.t_ns[0])).apply_block(
                block
            )
            out = run(CnnMapDetector, {"mapping_test": "off"}, array, block, (0.0, 10.0))
            t = block.t_s()
            after = out.alarm & (t >= 15.0) & (t < 16.0)
            hits = np.flatnonzero(after)
            column = array.sensor_ids("accel").index("imu5.accel.x")
            rows.append(
                (
                    hits.size,
                    t[hits[-1]] - 15.0 + 0.01 if hits.size else 0.0,
                    (out.isolated[after] == column).mean() if hits.size else np.nan,
                )
            )
        r = np.array(rows, dtype=float)
        right = f"{np.nanmean(r[:, 2]):.0%}" if np.any(r[:, 0] > 0) else "-"
        print(
            f"| {amp:g} m/s^2 ({amp / 0.03:.1f} sigma) | {int(np.sum(r[:, 0] > 0))}/{seeds} |"
            f" {r[:, 0].mean():.1f} ({r[:, 0].max():.0f}) | {r[:, 1].max():.2f} | {right} |",
            flush=True,
        )


def _former_threshold(level, design, margin, dof, rng, chains=256, steps=16384, window=1):
    """cusum_threshold as it was first written: index arrays, a new array per sample of
    the recursion, two full runs, full sorts."""

    def residual(series):
        cumulative = np.concatenate([np.zeros((1, series.shape[1])), np.cumsum(series, axis=0)])
        out = np.full(series.shape, np.nan)
        rows = np.arange(window, series.shape[0])
        means = (cumulative[rows] - cumulative[rows - window]) / window
        out[window:] = (series[rows] - means) / math.sqrt(1.0 + 1.0 / window)
        return out

    def recursion(increments, cap):
        out = np.empty_like(increments)
        current = np.zeros(increments.shape[1])
        for i in range(increments.shape[0]):
            current = np.minimum(np.maximum(current + increments[i], 0.0), cap)
            out[i] = current
        return out

    def tail(values, cap=math.inf):
        flat = np.sort(values.ravel())[::-1]
        n = flat.size
        if level * n >= 100:
            return float(flat[int(level * n)])
        counts = np.unique(np.geomspace(100, 0.05 * n, 24).astype(np.int64))
        heights = flat[counts]
        keep = heights < cap - 1e-9
        heights, probabilities = heights[keep], counts[keep] / n
        upper = slice(len(heights) // 2, None)
        slope, intercept = np.polyfit(heights[upper], np.log(probabilities[upper]), 1)
        if not slope < 0:
            return float(flat[100])
        return float((math.log(level) - intercept) / slope)

    burn = 1024
    scale = np.sqrt(np.maximum(1.0 + rng.normal(0.0, math.sqrt(2.0 / dof), chains), 0.05))
    white = rng.standard_normal((steps + burn + window, chains))
    z = residual(white)[window:] / scale
    increments = design.increments(z)
    h = tail(recursion(increments, math.inf)[burn:])
    return tail(recursion(increments, h + margin)[burn:], h + margin)


def _former_input_gradients(network, x):
    """Sequential.input_gradients as first written: a forward pass and a full backward pass
    (parameter gradients included) per output."""
    outputs = network.forward(x)
    jacobian = np.empty((x.shape[0], outputs.shape[1], *x.shape[1:]))
    for o in range(outputs.shape[1]):
        network.forward(x)
        seed = np.zeros_like(outputs)
        seed[:, o] = 1.0
        jacobian[:, o] = network.backward(seed)
    return jacobian


def _cpu(function, repeats):
    """Median process CPU time of ``repeats`` calls, s, and the last result."""
    times, result = [], None
    for _ in range(repeats):
        start = time.process_time()
        result = function()
        times.append(time.process_time() - start)
    return float(np.median(times)), result


def library_part(repeats: int = 5) -> None:
    print(f"## library costs of a cnn-map fit (median CPU of {repeats}; load {os.getloadavg()})")
    # the input test's setting on wearable12 (seed 0): alpha 0.001 over 36 channels, W = 8,
    # a 0.25 s release at 100 Hz, the calibration's degrees of freedom
    level = -math.expm1(math.log1p(-0.001) / 36)
    margin = 0.25 * 100.0 * (INPUT_DESIGN.offset - INPUT_DESIGN.gain)
    design = CusumDesign(INPUT_DESIGN.ratio, INPUT_DESIGN.clip)
    args = (level, design, margin, 132.0354088144793)
    former, h_former = _cpu(
        lambda: _former_threshold(*args, np.random.default_rng([0, 0x1C5]), window=8), repeats
    )
    now, h_now = _cpu(
        lambda: cusum_threshold(*args, np.random.default_rng([0, 0x1C5]), mean_window=8), repeats
    )
    assert h_now == h_former, (h_now, h_former)
    print(
        f"cusum_threshold: {now:.3f} s CPU, former {former:.3f} s, ratio {former / now:.2f}"
        f" (h = {h_now!r}, identical)"
    )
    mapping = MappingNetwork(
        input_length=24,
        filters=8,
        kernel=5,
        activation="relu",
        rate_hz=100.0,
        input_mean=np.zeros(3),
        input_std=np.ones(3),
        output_mean=np.zeros(3),
        output_std=np.ones(3),
    )
    network = mapping.build(np.random.default_rng(1))
    x = np.random.default_rng(2).standard_normal((2048, 24, 3))
    former, j_former = _cpu(lambda: _former_input_gradients(network, x), repeats)
    now, j_now = _cpu(lambda: network.input_gradients(x), repeats)
    assert np.array_equal(j_now, j_former)
    print(
        f"input_gradients (2048 windows): {now:.3f} s CPU, former {former:.3f} s,"
        f" ratio {former / now:.2f} (identical)"
    )
    print(f"load after: {os.getloadavg()}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seeds", type=int, default=20)
    parts = ("all", "speed", "table", "mapping-level", "input-step", "library")
    parser.add_argument("--part", choices=parts, default="all")
    parser.add_argument(
        "--first-seed", type=int, default=12000, help="of --part mapping-level, input-step"
    )
    args = parser.parse_args()
    if args.part == "mapping-level":
        mapping_level_part(args.first_seed, args.seeds)
        return
    if args.part == "input-step":
        input_step_part(args.first_seed, args.seeds)
        return
    if args.part == "library":
        library_part()
        return
    if args.part in ("all", "speed"):
        speed_part()
    if args.part in ("all", "table"):
        table_part(args.seeds)


if __name__ == "__main__":
    main()
