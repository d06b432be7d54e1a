"""Peak memory of ``imufdi report`` on a log and on a 10x longer one, same run.

Usage: python benchmarks/bench_report.py [--minutes 10] [--imus 16] [--factor 10] [--no-imu]
[--match-budget 1/h]

Writes two annotated logs shaped like ``imufdi detect -d glt`` output on a 16-IMU, 100 Hz
array (the IMU channels, per-sample FdiStatus channels for gyro and accel with 48 isolation
scores each, an injected step in the truth record and the detect record with its
calibration window), then runs ``imufdi report LOG --match-far 1% --json FILE`` in a fresh
process on each and prints ru_maxrss and the ratio long/short (target <= 1.1: the report
streams, memory does not grow with the log length), with the load average. Status values
are random; the report's work (decoding, metrics, sweep histograms) does not depend on them.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from imufdi_cli.array import ArrayConfig
from imufdi_cli.detectors.base import DetectionBlock
from imufdi_cli.log import ImuBlock
from imufdi_cli.mcapio import (
    ImuArrayWriter,
    McapWriter,
    encode_status,
    register_status_channel,
)

RATE_HZ = 100.0
T0_NS = 1_700_000_000 * 10**9


def make_log(path: Path, n_imus: int, n_samples: int, with_imu: bool, block: int = 20_000) -> None:
    """An annotated log of ``n_samples`` samples (see module docstring)."""
    rng = np.random.default_rng(0)
    array = ArrayConfig.co_aligned(n_imus, RATE_HZ)
    period = round(1e9 / RATE_HZ)
    onset = n_samples // 2
    with McapWriter(path) as writer:
        imu_writer = ImuArrayWriter(writer, array) if with_imu else None
        channels = {
            s: register_status_channel(writer, "glt", s, array.sensor_ids(s))
            for s in ("gyro", "accel")
        }
        for start in range(0, n_samples, block):
            n = min(block, n_samples - start)
            t_ns = T0_NS + np.arange(start, start + n, dtype=np.int64) * period
            if imu_writer is not None:
                imu_writer.write_block(
                    ImuBlock(
                        t_ns=t_ns,
                        gyro=rng.normal(0, 0.003, (n, n_imus, 3)),
                        accel=rng.normal(0, 0.02, (n, n_imus, 3)) + np.array([0.0, 0.0, 9.81]),
                    )
                )
            for sensor_type, cid in channels.items():
                n_s = 3 * n_imus
                stat = rng.chisquare(n_s - 3, n)
                if sensor_type == "gyro":
                    stat = stat + np.where(np.arange(start, start + n) >= onset, 30.0, 0.0)
                det = DetectionBlock(
                    statistic=stat,
                    threshold=np.full(n, 66.2),
                    alarm=stat > 66.2,
                    isolated=np.where(stat > 66.2, 0, -1).astype(np.int32),
                    amplitude=np.full(n, np.nan),
                    scores=rng.chisquare(1, (n, n_s)),
                )
                writer.add_batch(encode_status(cid, t_ns, det))
        writer.add_metadata("imufdi.array", {"json": array.to_json()})
        write_step_truth_and_detect(writer, onset / RATE_HZ)


def write_step_truth_and_detect(writer: McapWriter, onset_s: float) -> None:
    """The truth of a 0.9 deg/s step on imu0.gyro.x from ``onset_s`` on and glt's detect
    record (calibration window: the first 2 s), as ``inject`` and ``detect`` write them."""
    fault = {
        "id": "f0",
        "model": "step",
        "sensors": ["imu0.gyro.x"],
        "params": {"amp": 0.0157},
        "at_s": onset_s,
        "until_s": None,
        "spec": f"step:imu0.gyro.x,at={onset_s}s,amp=0.9deg/s",
    }
    record = {"format": "imufdi.faults/1", "seed": 0, "t0_ns": T0_NS, "faults": [fault]}
    writer.add_metadata("imufdi.faults", {"json": json.dumps(record)})
    detect = {"detector": "glt", "calibration_window_ns": [T0_NS, T0_NS + 2 * 10**9]}
    writer.add_metadata("imufdi.detect.glt", {"json": json.dumps(detect)})


def peak_rss_report(path: Path, out: Path, extra: list[str] | None = None) -> tuple[int, float]:
    """Peak RSS (kB) and wall time of a fresh process running the report.

    The peak is VmHWM from /proc/self/status where there is one: ru_maxrss survives
    fork + exec on Linux, so it would include this (parent) process, which grows while it
    writes the long log."""
    code = (
        "import resource, sys\n"
        "from imufdi_cli.cli import main\n"
        "try:\n"
        "    main(['report', sys.argv[1], '--match-far', '1%', '--json', sys.argv[2],"
        " *sys.argv[3:]])\n"
        "except SystemExit as exc:\n"
        "    assert not exc.code, exc.code\n"
        "peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss\n"
        "try:\n"
        "    with open('/proc/self/status') as f:\n"
        "        peak = next(int(l.split()[1]) for l in f if l.startswith('VmHWM:'))\n"
        "except (OSError, StopIteration):\n"
        "    pass\n"
        "print(peak, file=sys.stderr)\n"
    )
    t0 = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-c", code, str(path), str(out), *(extra or [])],
        check=True,
        capture_output=True,
        text=True,
    )
    return int(done.stderr.strip().splitlines()[-1]), time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--minutes", type=float, default=10.0, help="short log length")
    parser.add_argument("--imus", type=int, default=16)
    parser.add_argument("--factor", type=int, default=10, help="long log = factor x short")
    parser.add_argument("--no-imu", action="store_true", help="status channels only")
    parser.add_argument(
        "--match-budget",
        metavar="RATE",
        help="also report --match-budget RATE (the false episodes at every budget level)",
    )
    args = parser.parse_args()
    extra = ["--match-budget", args.match_budget] if args.match_budget else []
    n_short = int(args.minutes * 60 * RATE_HZ)
    with tempfile.TemporaryDirectory() as tmp:
        rss = {}
        for label, n in (("1x", n_short), (f"{args.factor}x", n_short * args.factor)):
            path = Path(tmp) / f"{label}.mcap"
            t0 = time.perf_counter()
            make_log(path, args.imus, n, not args.no_imu)
            made = time.perf_counter() - t0
            peak, wall = peak_rss_report(path, Path(tmp) / f"{label}.json", extra)
            rss[label] = peak
            size = path.stat().st_size / 1e6
            print(
                f"report {label}: {n} samples x {args.imus} IMUs ({n / RATE_HZ / 60:.0f} min,"
                f" {size:.0f} MB, made in {made:.0f} s): peak RSS {peak / 1024:.0f} MiB,"
                f" {wall:.1f} s"
            )
            path.unlink()
    ratio = rss[f"{args.factor}x"] / rss["1x"]
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    verdict = "ok" if ratio <= 1.1 else "MISSED"
    print(f"peak RSS {args.factor}x / 1x = {ratio:.3f} (target <= 1.1: {verdict}); load {load}")


if __name__ == "__main__":
    main()
