"""Benchmark: MVMD speed against the straightforward transcription, many windows in one
batched call against one call each, and the whole
woa-mvmd-glt detector on paper-table4 (tuning included), with FAR/MAR/FIR and the drift
detection delay against a plain per-sample GLT, over seeds.

Run: python benchmarks/bench_mvmd.py [--seeds 20]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np
from scipy.stats import chi2

sys.path.insert(0, str(Path(__file__).parent / "reference"))
from mvmd_reference import mvmd_reference

from imufdi_cli.detectors.base import DetectionBlock, parse_params
from imufdi_cli.detectors.mvmd import channel_power, mvmd, mvmd_gains, spectrum
from imufdi_cli.detectors.woa_mvmd_glt import WoaMvmdGltDetector
from imufdi_cli.faults import FaultInjector, active_mask, parse_fault_spec
from imufdi_cli.log import iter_blocks
from imufdi_cli.maths.parity import parity_matrix, residual_sigma, residuals, whiten
from imufdi_cli.simulate import PRESETS, preset, simulate_block


def median_time(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def bench_mvmd() -> None:
    rng = np.random.default_rng(0)
    t = np.arange(500) / 100.0
    x = 0.17 + 0.0026 * rng.standard_normal((48, 500)) + 0.01 * np.sin(2 * np.pi * 3 * t)
    fast = mvmd(x, 4, 2000.0)
    fast_s = median_time(lambda: mvmd(x, 4, 2000.0), 9)
    ref_modes, _, ref_iter = mvmd_reference(x, 4, 2000.0)
    ref_s = median_time(lambda: mvmd_reference(x, 4, 2000.0), 1)
    diff = np.linalg.norm(ref_modes - fast.modes) / np.linalg.norm(x)
    print("MVMD 48 ch x 500 samples, K=4, alpha=2000, tol=1e-7")
    print(f"  imufdi mvmd      median {fast_s * 1e3:8.1f} ms  ({fast.n_iter} iterations)")
    print(f"  reference transc.       {ref_s * 1e3:8.1f} ms  ({ref_iter} iterations)")
    print(f"  ratio reference / imufdi: {ref_s / fast_s:.0f}x; relative mode difference {diff:.1e}")


def bench_windows(n_windows: int = 196) -> None:
    """The detector's case: many 50-sample windows of 16 channels (a 20 s block of
    paper-table4 at hop 10), one MVMD call per window against one batched call."""
    rng = np.random.default_rng(1)
    t = np.arange(50) / 100.0
    windows = 0.17 + 0.0026 * rng.standard_normal((n_windows, 16, 50))
    windows += 0.01 * np.sin(2 * np.pi * 3 * t)
    spectra = [spectrum(w) for w in windows]
    power = np.stack([channel_power(spec) for spec, _, _ in spectra])
    freqs = spectra[0][1]

    def one_at_a_time():
        return [mvmd_gains(p, freqs, [2], [550.0], tol=1e-6, max_iter=300) for p in power]

    def batched():
        count = len(power)
        return mvmd_gains(power, freqs, [2] * count, [550.0] * count, tol=1e-6, max_iter=300)

    single_s = median_time(one_at_a_time, 1)
    batch_s = median_time(batched, 3)
    same = all(
        np.array_equal(a[0][0], b[0]) and a[0][2] == b[2]
        for a, b in zip(one_at_a_time(), batched())
    )
    print(f"\nMVMD of {n_windows} windows, 16 ch x 50 samples, K=2, alpha=550, tol=1e-6")
    print(
        f"  one call per window {single_s * 1e3:8.1f} ms; one batched call {batch_s * 1e3:8.1f} ms"
    )
    print(f"  ratio {single_s / batch_s:.1f}x; identical gains and iteration counts: {same}")


def plain_glt(block, array, ncal, alpha=0.01):
    H = array.measurement_matrix("gyro")
    m = array.select(block.gyro, "gyro")
    sigma = residual_sigma(H, m[:ncal])
    bias = residuals(H, m[:ncal]).mean(axis=0)
    V = parity_matrix(whiten(H, sigma))
    p = ((m - bias) / sigma) @ V.T
    return (p * p).sum(axis=1) > chi2.ppf(1 - alpha, H.shape[0] - 3)


def run(seed: int, scenario: str):
    array, block = simulate_block(preset("paper-table4", seed=seed))
    faults = [parse_fault_spec(s, array) for s in PRESETS["paper-table4"].faults[scenario]]
    t0 = int(block.t_ns[0])
    injector = FaultInjector(faults, array, seed=seed, t0_ns=t0)
    faulty = injector.apply_block(block)
    ncal = int(2.0 * array.rate_hz)
    start = time.perf_counter()
    det = WoaMvmdGltDetector(**parse_params(WoaMvmdGltDetector.PARAMS, {}, "woa-mvmd-glt"))
    det.fit(block.slice(0, ncal), array)
    parts = [det.process(b)["gyro"] for b in iter_blocks(faulty, 64)]
    out = DetectionBlock.concatenate([*parts, det.flush()["gyro"]])
    seconds = time.perf_counter() - start
    truth = active_mask(injector.faults, array.sensor_ids("gyro"), faulty.t_ns, t0)
    any_fault = truth.any(axis=1)
    far = np.mean(out.alarm[~any_fault])
    mar = np.mean(~out.alarm[any_fault])
    detected = any_fault & out.alarm
    wrong = detected & ~truth[np.arange(len(out)), np.clip(out.isolated, 0, None)]
    fir = wrong.sum() / max(detected.sum(), 1)
    onset = int(np.flatnonzero(any_fault)[0])

    def delay(alarm):
        hits = np.flatnonzero(alarm[onset:])
        return hits[0] / array.rate_hz if hits.size else np.nan

    glt = plain_glt(faulty, array, ncal)
    glt_far = np.mean(glt[~any_fault])
    glt_mar = np.mean(~glt[any_fault])
    return far, mar, fir, delay(out.alarm), delay(glt), glt_far, glt_mar, seconds


def bench_detector(n_seeds: int) -> None:
    print(f"\nwoa-mvmd-glt on paper-table4, {n_seeds} seeds (defaults, tuning on 0-2 s included)")
    for scenario in ("step", "drift"):
        rows = np.array([run(seed, scenario) for seed in range(n_seeds)])
        far, mar, fir, delay, glt_delay, glt_far, glt_mar, seconds = np.nanmean(rows, axis=0)
        print(
            f"  {scenario:5s} FAR {100 * far:5.2f} %  MAR {100 * mar:5.2f} %  FIR {100 * fir:5.2f} %"
            f"  delay {delay:.3f} s | plain GLT: FAR {100 * glt_far:5.2f} %"
            f"  MAR {100 * glt_mar:5.2f} %  delay {glt_delay:.3f} s"
            f" | detector wall time mean {seconds:.2f} s, max {rows[:, 7].max():.2f} s"
        )


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, default=20)
    args = parser.parse_args()
    print(f"load average {os.getloadavg()}")
    bench_mvmd()
    bench_windows()
    bench_detector(args.seeds)
    print(f"load average after {os.getloadavg()}")
