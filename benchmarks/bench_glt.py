"""Throughput of the GLT detector on a 16-IMU, 100 Hz, 1-hour log (360,000 samples).

The log is made at run time with numpy (turntable rate + white noise, gyro and accel).
Figures: array samples per second of ``GltDetector.process`` (both sensor types, 48 gyros
and 48 accelerometers) in streaming blocks, and, as a baseline measured in the same run,
a naive per-sample implementation of the same maths (p = V m, (V V^T)^-1 by
``np.linalg.solve`` per sample, D_FD and every D_FI,i) on a subset of samples.

Calibration (``fit`` on the 200-sample window, both sensor types), timed ``--fits`` times
alternating with a baseline in the same run: the same fit with the estimated-sigma
threshold's derivatives taken by central differences (step 1e-3, 2n + 1 pseudo-inverses,
the former implementation) instead of the analytic form; prints the CPU per fit,
the ratio, the thresholds' largest relative difference and the load average.

Run: ``python benchmarks/bench_glt.py [--block 10000] [--fits 20]``. BLAS is pinned to one thread
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

import imufdi_cli.detectors.glt as glt_module
from imufdi_cli.array import ArrayConfig
from imufdi_cli.detectors.base import parse_params
from imufdi_cli.detectors.glt import GltDetector
from imufdi_cli.log import ImuBlock
from imufdi_cli.maths.parity import parity_matrix, whiten

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


def central_difference_threshold(
    h_white: np.ndarray, alpha: float, scale_variance: np.ndarray | None, mean_samples: float
) -> tuple[float, float, float]:
    """Baseline: the former ``parity.estimated_sigma_threshold`` (derivatives of the
    traces by central differences, step 1e-3, one pseudo-inverse per evaluation)."""
    from imufdi_cli.maths.parity import two_moment_threshold

    def traces(delta: np.ndarray) -> np.ndarray:
        weights = 1.0 / np.sqrt(1.0 + delta)
        h_est = weights[:, None] * h_white
        projector = np.eye(h_white.shape[0]) - h_est @ np.linalg.pinv(h_est)
        form = weights[:, None] * projector * weights[None, :]
        return np.array([np.trace(form), np.sum(form * form.T)])

    n = h_white.shape[0]
    base = traces(np.zeros(n))
    mean, square, spread = base[0], base[1], 0.0
    if scale_variance is not None:
        step = 1e-3
        for j in range(n):
            delta = np.zeros(n)
            delta[j] = step
            up, down = traces(delta), traces(-delta)
            second = (up + down - 2.0 * base) / step**2
            first = (up[0] - down[0]) / (2.0 * step)
            mean += 0.5 * second[0] * scale_variance[j]
            square += 0.5 * second[1] * scale_variance[j]
            spread += first**2 * scale_variance[j]
    return two_moment_threshold(mean, square, spread, alpha, mean_samples)


def time_fits(array: ArrayConfig, log: ImuBlock, repeats: int) -> None:
    """CPU of glt's calibration, analytic threshold against the central-difference baseline."""
    window = log.slice(0, 200)
    analytic = glt_module.estimated_sigma_threshold
    cpu = {"analytic": 0.0, "central differences": 0.0}
    thresholds: dict[str, list[float]] = {"analytic": [], "central differences": []}
    for _ in range(repeats):
        for name, function in (
            ("analytic", analytic),
            ("central differences", central_difference_threshold),
        ):
            glt_module.estimated_sigma_threshold = function  # type: ignore[assignment]
            try:
                detector = GltDetector(**parse_params(GltDetector.PARAMS, {}, "glt"))
                start = time.process_time()
                detector.fit(window, array)
                cpu[name] += time.process_time() - start
            finally:
                glt_module.estimated_sigma_threshold = analytic  # type: ignore[assignment]
            thresholds[name] = [
                float(state.config.threshold) for state in detector._states.values()
            ]
    difference = max(
        abs(a / b - 1.0) for a, b in zip(thresholds["analytic"], thresholds["central differences"])
    )
    per_fit = {name: 1e3 * value / repeats for name, value in cpu.items()}
    print(
        f"glt fit (200 samples, gyro + accel), {repeats} fits each, alternating: analytic"
        f" {per_fit['analytic']:.1f} ms CPU, central differences {per_fit['central differences']:.1f}"
        f" ms CPU, ratio {per_fit['central differences'] / per_fit['analytic']:.1f}x;"
        f" thresholds differ by {difference:.1e} relative; load {os.getloadavg()[0]:.2f}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--block", type=int, default=10_000, help="samples per process() call")
    parser.add_argument("--naive", type=int, default=3_000, help="samples for the baseline")
    parser.add_argument("--fits", type=int, default=20, help="calibrations timed per variant")
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    array, log = make_log(rng)
    time_fits(array, log, args.fits)
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
