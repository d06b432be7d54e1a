"""Benchmark: glt's sequential test under a false-alarm budget (``--false-alarms 1/h``), the
CUSUM bank and its threshold search, against another checkout in the same run.

Log (made at run time, simulation seed 1, a tuning seed): paper-table4, 16 IMUs, 100 Hz,
``--minutes`` long (10 by default), with a 0.9 deg/s gyro step from 30 % of it and a
0.01 deg/s^2 gyro drift from 50 % (added to the simulated samples). Each child process
fits glt (``false_alarms=1/h``) on the first 2 s, as ``imufdi detect`` does by default, then
streams the rest in blocks of 4,096 samples (the reader's default block up to 16 IMUs); it prints the
process CPU of the fit (threshold search, calibration) and of the stream (the bank), and a
digest of every output array.

With ``--baseline TREE`` (e.g. ``git worktree add /tmp/base main``) every round runs this
tree and the baseline in turn (interleaved: a change of load hits both alike); the figures
are the minimum over ``--repeat`` rounds, printed with the load average, with this tree's
CPU over the baseline's and whether the outputs are the same bytes.

    python benchmarks/bench_sequential.py --baseline /tmp/base
    python benchmarks/bench_sequential.py --minutes 3 --repeat 5
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np

HERE = Path(__file__).resolve().parent
TREE = HERE.parent
BLOCK = 4096
CALIBRATION_S = 2.0


def make_log(directory: Path, minutes: float) -> None:
    """The simulated log's samples (``log.npz``) and its array config (``array.toml``)."""
    from imufdi_cli.simulate import preset, simulate_block

    array, block = simulate_block(preset("paper-table4", seed=1, duration=minutes * 60.0))
    gyro = np.array(block.gyro, dtype=float)
    n = gyro.shape[0]
    t = np.arange(n) / array.rate_hz
    gyro[int(0.3 * n) :, 3, 0] += np.deg2rad(0.9)  # a step on imu3.gyro.x
    late = slice(int(0.5 * n), None)
    gyro[late, 7, 1] += np.deg2rad(0.01) * (t[late] - t[late][0])  # a drift on imu7.gyro.y
    np.savez(directory / "log.npz", t_ns=block.t_ns, gyro=gyro, accel=block.accel)
    array.save(directory / "array.toml")


def child(directory: Path) -> None:
    """Fit and stream glt under the budget; print CPU seconds and the outputs' digest."""
    from imufdi_cli.array import ArrayConfig
    from imufdi_cli.detectors.glt import GltDetector
    from imufdi_cli.log import ImuBlock

    array = ArrayConfig.load(directory / "array.toml")
    data = np.load(directory / "log.npz")
    block = ImuBlock(t_ns=data["t_ns"], gyro=data["gyro"], accel=data["accel"])
    calibration = round(CALIBRATION_S * array.rate_hz)
    detector = GltDetector(false_alarms=1.0 / 3600.0)
    start = time.process_time()
    detector.fit(block.slice(0, calibration), array)
    fitted = time.process_time()
    digest = hashlib.sha256()
    for lo in range(calibration, len(block), BLOCK):
        out = detector.process(block.slice(lo, min(len(block), lo + BLOCK)))
        for sensor_type in sorted(out):
            rows = out[sensor_type]
            for name in ("statistic", "threshold", "alarm", "isolated", "amplitude", "scores"):
                digest.update(np.ascontiguousarray(getattr(rows, name)).tobytes())
    done = time.process_time()
    print(
        json.dumps({"fit": fitted - start, "stream": done - fitted, "digest": digest.hexdigest()})
    )


def run(tree: Path, directory: Path) -> dict[str, float | str]:
    env = dict(os.environ, PYTHONPATH=str(tree), OPENBLAS_NUM_THREADS="1")
    result = subprocess.run(
        [sys.executable, str(Path(__file__).resolve()), "--child", str(directory)],
        env=env,
        cwd=tree,
        capture_output=True,
        text=True,
        check=True,
    )
    parsed: dict[str, float | str] = json.loads(result.stdout.strip().splitlines()[-1])
    return parsed


def load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--minutes", type=float, default=10.0, help="length of the log")
    parser.add_argument("--repeat", type=int, default=5, help="interleaved rounds (min kept)")
    parser.add_argument("--baseline", type=Path, help="another checkout, run interleaved")
    parser.add_argument("--child", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child is not None:
        child(args.child)
        return 0
    trees = {"this": TREE}
    if args.baseline is not None:
        trees["baseline"] = args.baseline.resolve()
    with tempfile.TemporaryDirectory(prefix="imufdi-bench-sequential-") as name:
        directory = Path(name)
        make_log(directory, args.minutes)
        print(f"load average before: {load()} ({os.cpu_count()} cores)")
        print(f"log: paper-table4, 16 IMUs, 100 Hz, {args.minutes:g} min, gyro step and drift")
        results: dict[str, list[dict[str, float | str]]] = {tree: [] for tree in trees}
        for round_index in range(args.repeat):
            for tree_name, tree in trees.items():
                results[tree_name].append(run(tree, directory))
            print(f"round {round_index + 1}/{args.repeat} done, load average {load()}")
    best = {
        tree: {part: min(float(r[part]) for r in runs) for part in ("fit", "stream")}
        for tree, runs in results.items()
    }
    for tree, parts in best.items():
        print(
            f"{tree:8s} ({trees[tree]}): CPU s (min of {args.repeat}) fit {parts['fit']:.3f}"
            f"  stream {parts['stream']:.3f}  total {parts['fit'] + parts['stream']:.3f}"
        )
    if "baseline" in trees:
        for part in ("fit", "stream"):
            ratio = best["this"][part] / best["baseline"][part]
            print(f"this / baseline {part:6s} {ratio:5.2f}x")
        total = sum(best["this"].values()) / sum(best["baseline"].values())
        print(f"this / baseline total  {total:5.2f}x")
        digests = {str(r["digest"]) for runs in results.values() for r in runs}
        print(f"outputs: {'the same bytes' if len(digests) == 1 else 'DIFFERENT'} in every run")
    print(f"load average after: {load()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
