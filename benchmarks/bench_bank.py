"""Speed of the bank-of-estimators detector on a 100 Hz quadrotor-marg log.

Prints the processing time of the accel/mag/gyro bank (seven batched Gauss-Newton attitude
estimators + gyro residuals) against the log duration (real-time factor, goal >= 50x), and
as baseline, measured in the same run, the time of one scipy.optimize.least_squares call
per sample for the same seven estimators on a subset of samples (extrapolated per sample).

Usage: python benchmarks/bench_bank.py [--duration 60] [--block 1000]
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
from scipy.optimize import least_squares

from imufdi_cli.detectors.attitude import predict_measurements
from imufdi_cli.detectors.bank import ESTIMATOR_MASKS, BankDetector
from imufdi_cli.log import iter_blocks
from imufdi_cli.simulate import preset, simulate_block


def best_of(repeats: int, run) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        run()
        times.append(time.perf_counter() - start)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=60.0, help="log length, s")
    parser.add_argument("--block", type=int, default=1000, help="samples per process() call")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()

    config = preset("quadrotor-marg", seed=1, duration=f"{args.duration}s")
    array, block = simulate_block(config)
    log_seconds = len(block) / array.rate_hz

    def run_bank() -> None:
        detector = BankDetector()
        detector.fit(block.slice(0, 200), array)
        for piece in iter_blocks(block, args.block):
            detector.process(piece)

    bank_seconds = best_of(args.repeats, run_bank)

    # Baseline: one scipy least_squares call per sample and estimator (rotation vector).
    detector = BankDetector()
    detector.fit(block.slice(0, 200), array)
    model = detector._model
    assert model is not None
    y = model.normalised(block, array)
    subset = y[:: max(1, len(y) // 100)][:100]

    def run_baseline() -> None:
        for sample in subset:
            for mask in ESTIMATOR_MASKS:
                weights = np.sqrt(mask) / model.noise

                def residual(rotvec: np.ndarray, sample=sample, weights=weights) -> np.ndarray:
                    angle = np.linalg.norm(rotvec)
                    axis = rotvec / angle if angle > 0 else np.zeros(3)
                    q = np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis])
                    predicted, _ = predict_measurements(q, model.sensor_axes, model.references)
                    return weights * (sample - predicted)

                least_squares(residual, np.zeros(3))

    baseline_seconds = best_of(1, run_baseline) * len(y) / len(subset)
    print(f"log: {len(block)} samples, {log_seconds:.1f} s at {array.rate_hz:.0f} Hz")
    print(
        f"bank (block {args.block}): {bank_seconds:.3f} s -> {log_seconds / bank_seconds:.0f}x real time"
    )
    print(
        f"baseline (per-sample scipy least_squares, extrapolated): {baseline_seconds:.2f} s"
        f" -> {log_seconds / baseline_seconds:.1f}x real time"
    )
    print(f"speed-up of the batched bank over the baseline: {baseline_seconds / bank_seconds:.0f}x")
    print(f"load average (1, 5, 15 min): {' '.join(f'{v:.1f}' for v in os.getloadavg())}")


if __name__ == "__main__":
    main()
