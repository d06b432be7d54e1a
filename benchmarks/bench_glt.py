"""Throughput of the GLT detector on a 16-IMU, 100 Hz, 1-hour log (360,000 samples).

The log is made at run time with numpy (turntable rate + white noise, gyro and accel).
Figures: array samples per second of ``GltDetector.process`` (both sensor types, 48 gyros
and 48 accelerometers) in streaming blocks, and, as a baseline measured in the same run,
a naive per-sample implementation of the same maths (p = V m, (V V^T)^-1 by
``np.linalg.solve`` per sample, D_FD and every D_FI,i) on a subset of samples.

Run: ``python benchmarks/bench_glt.py [--block 10000]``. BLAS is pinned to one thread
unless OPENBLAS_NUM_THREADS is set: the products are thin ((N, n) x (n, 3)) and a
multi-threaded OpenBLAS on a busy 2-core machine was 10-20x slower on them. Both wall-clock
and process CPU time are printed (CPU time is less sensitive to other load on the machine).
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np

from imufdi_cli.array import ArrayConfig
from imufdi_cli.detectors.base import parse_params
from imufdi_cli.detectors.glt import GltDetector
from imufdi_cli.detectors.parity import parity_matrix, whiten
from imufdi_cli.log import ImuBlock

N_IMUS = 16
RATE_HZ = 100.0
N_SAMPLES = 360_000  # 1 hour
GYRO_SIGMA = np.deg2rad(0.15)
ACCEL_SIGMA = 0.02


def make_log(rng: np.random.Generator) -> tuple[ArrayConfig, ImuBlock]:
    array = ArrayConfig.co_aligned(N_IMUS, RATE_HZ)
    t = np.arange(N_SAMPLES) / RATE_HZ
    rate = np.deg2rad(10.0) * np.ones((N_SAMPLES, 1, 3))
    gyro = rate + GYRO_SIGMA * rng.standard_normal((N_SAMPLES, N_IMUS, 3))
    accel = np.array([0.0, 0.0, 9.81]) + ACCEL_SIGMA * rng.standard_normal((N_SAMPLES, N_IMUS, 3))
    gyro[N_SAMPLES // 2 :, 0, 0] += np.deg2rad(0.9)  # one step fault half way
    return array, ImuBlock(t_ns=(t * 1e9).astype(np.int64), gyro=gyro, accel=accel)


def naive_glt(values: np.ndarray, V: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Per-sample loop: p = V m, G = (V V^T)^-1 via solve, D_FD and argmax D_FI."""
    isolated = np.empty(values.shape[0], dtype=np.intp)
    gram = V @ V.T
    for k in range(values.shape[0]):
        p = V @ (values[k] / sigma)
        weighted = np.linalg.solve(gram, p)
        d_fd = p @ weighted
        d_fi = (weighted @ V) ** 2 / np.einsum("ij,ij->j", V, np.linalg.solve(gram, V))
        isolated[k] = int(np.argmax(d_fi)) if d_fd > 0 else -1
    return isolated


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--block", type=int, default=10_000, help="samples per process() call")
    parser.add_argument("--naive", type=int, default=3_000, help="samples for the baseline")
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    array, log = make_log(rng)
    detector = GltDetector(**parse_params(GltDetector.PARAMS, {}, "glt"))
    detector.fit(log.slice(0, 200), array)

    start, start_cpu = time.perf_counter(), time.process_time()
    alarms = 0
    for first in range(0, N_SAMPLES, args.block):
        out = detector.process(log.slice(first, first + args.block))
        alarms += int(out["gyro"].alarm.sum())
    vectorised_s = time.perf_counter() - start
    vectorised_cpu = time.process_time() - start_cpu
    vectorised_rate = N_SAMPLES / vectorised_s

    gyro_values = array.select(log.gyro[: args.naive], "gyro")  # type: ignore[index]
    sigma = np.full(gyro_values.shape[1], GYRO_SIGMA)
    V = parity_matrix(whiten(array.measurement_matrix("gyro"), sigma))
    start, start_cpu = time.perf_counter(), time.process_time()
    naive_glt(gyro_values, V, sigma)
    naive_s = time.perf_counter() - start
    naive_cpu = time.process_time() - start_cpu
    naive_rate = args.naive / naive_s / 2.0  # one sensor type timed; both types = 2x work
    naive_cpu_rate = args.naive / naive_cpu / 2.0

    print(
        f"log: {N_IMUS} IMUs x (3 gyro + 3 accel), {N_SAMPLES} samples ({N_SAMPLES / RATE_HZ:.0f} s)"
    )
    print(f"BLAS threads: {os.environ['OPENBLAS_NUM_THREADS']}")
    print(
        f"glt process, block {args.block}: {vectorised_s:.3f} s wall, {vectorised_rate:,.0f}"
        f" array samples/s; CPU {vectorised_cpu:.3f} s, {N_SAMPLES / vectorised_cpu:,.0f} samples/s"
    )
    print(f"  gyro alarm samples: {alarms} (fault on the second half: {N_SAMPLES // 2} samples)")
    print(
        f"naive per-sample loop ({args.naive} samples, per type x2): {naive_rate:,.0f}"
        f" samples/s wall, {naive_cpu_rate:,.0f} CPU"
    )
    print(f"speed-up: {vectorised_rate / naive_rate:,.0f}x wall")
    cpu_rate = N_SAMPLES / vectorised_cpu
    print(
        f"target >= 1,000,000 samples/s: wall {'met' if vectorised_rate >= 1e6 else 'NOT met'},"
        f" CPU {'met' if cpu_rate >= 1e6 else 'NOT met'}"
    )


if __name__ == "__main__":
    main()
