"""What ``--plot`` adds to ``imufdi report`` on a long log (the report figure's cost).

Usage::

    python benchmarks/bench_plot.py [--minutes 10] [--imus 16] [--rate 100] [--repeat 3]
        [--baseline DIR]

Writes, at run time, a status-only log shaped like ``imufdi detect -d glt`` output on an
``--imus`` array at ``--rate`` Hz (gyro and accel FdiStatus channels with 3 x imus
isolation scores each, the truth of a step on imu0.gyro.x from the middle on, single-sample
spikes of the statistic, the detect record with its calibration window), then runs
``imufdi report LOG -q`` and ``imufdi report LOG -q --plot FILE`` alternately, each in a
fresh process, ``--repeat`` times. Prints the CPU time (user + system of the child) and
wall time of every run, the ratio plot / no plot of the median CPU times and the figure's
own cost (the median difference), with the load average.

``--baseline DIR`` (a directory holding another version's ``imufdi_cli``, e.g. an export
of main: ``git archive main | tar -x -C DIR``) also runs that version's two commands in
the same loop and prints the figure cost of this version against it.

The report keeps at most 20 000 to 40 000 samples per channel for the figure
(docs/metrics.md, Memory), so the figure's work is nearly the same at 100 Hz and 1 kHz;
the report's own pass grows with the log.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from bench_report import T0_NS, write_step_truth_and_detect  # the same truth and detect record

from imufdi_cli.array import ArrayConfig
from imufdi_cli.detectors.base import DetectionBlock
from imufdi_cli.mcapio import McapWriter, encode_status, register_status_channel

ENV = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
THRESHOLD = 66.2


def make_log(path: Path, n_imus: int, n_samples: int, rate_hz: float, block: int = 20_000) -> None:
    """The annotated status-only log of the module docstring (values random, seed 0)."""
    rng = np.random.default_rng(0)
    array = ArrayConfig.co_aligned(n_imus, rate_hz)
    period = round(1e9 / rate_hz)
    onset = n_samples // 2
    spikes = set(rng.choice(n_samples, size=20, replace=False).tolist())
    with McapWriter(path) as writer:
        channels = {
            s: register_status_channel(writer, "glt", s, array.sensor_ids(s))
            for s in ("gyro", "accel")
        }
        for start in range(0, n_samples, block):
            n = min(block, n_samples - start)
            index = np.arange(start, start + n)
            t_ns = T0_NS + index * period
            for sensor_type, cid in channels.items():
                n_s = 3 * n_imus
                stat = rng.chisquare(n_s - 3, n)
                if sensor_type == "gyro":
                    stat = stat + np.where(index >= onset, 30.0, 0.0)
                    for k in spikes.intersection(index.tolist()):
                        stat[k - start] = 1e4  # one-sample spikes: must stay on the figure
                alarm = stat > THRESHOLD
                scores = rng.chisquare(1, (n, n_s))
                if sensor_type == "gyro":
                    scores[index >= onset, 0] += 20.0
                det = DetectionBlock(
                    statistic=stat,
                    threshold=np.full(n, THRESHOLD),
                    alarm=alarm,
                    isolated=np.where(alarm, np.argmax(scores, axis=1), -1).astype(np.int32),
                    amplitude=np.full(n, np.nan),
                    scores=scores,
                )
                writer.add_batch(encode_status(cid, t_ns, det))
        writer.add_metadata("imufdi.array", {"json": array.to_json()})
        write_step_truth_and_detect(writer, onset / rate_hz)


def timed(args: list[str], tree: str | None) -> tuple[float, float]:
    """(CPU seconds, wall seconds) of ``imufdi ARGS`` in a fresh process of ``tree``'s
    imufdi_cli (None: this one's)."""
    env = ENV if tree is None else {**ENV, "PYTHONPATH": os.path.abspath(tree)}
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    subprocess.run(
        [sys.executable, "-m", "imufdi_cli", *args],
        check=True,
        env=env,
        cwd=tree,
        stdout=subprocess.DEVNULL,
    )
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return cpu, wall


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--imus", type=int, default=16)
    parser.add_argument("--rate", type=float, default=100.0, help="status rate, Hz")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--baseline", help="directory of another version's imufdi_cli")
    args = parser.parse_args()
    n = int(args.minutes * 60 * args.rate)
    versions: dict[str, str | None] = {"this": None}
    if args.baseline:
        versions["baseline"] = args.baseline
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "status.mcap"
        t0 = time.perf_counter()
        make_log(log, args.imus, n, args.rate)
        print(
            f"log: {n} samples x {args.imus} IMUs at {args.rate:g} Hz ({args.minutes:g} min,"
            f" {log.stat().st_size / 1e6:.0f} MB, made in {time.perf_counter() - t0:.0f} s)"
        )
        cpu: dict[tuple[str, bool], list[float]] = {}
        for _ in range(args.repeat):
            for name, tree in versions.items():
                for plot in (False, True):
                    extra = ["--plot", str(Path(tmp) / f"{name}.png")] if plot else []
                    c, w = timed(["report", str(log.resolve()), "-q", *extra], tree)
                    cpu.setdefault((name, plot), []).append(c)
                    label = "report --plot" if plot else "report       "
                    print(f"  {name:8s} {label}: CPU {c:6.2f} s, wall {w:6.2f} s")
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    cost = {}
    for name in versions:
        base = statistics.median(cpu[(name, False)])
        with_plot = statistics.median(cpu[(name, True)])
        cost[name] = with_plot - base
        print(
            f"{name}: median CPU report {base:.2f} s, report --plot {with_plot:.2f} s:"
            f" ratio {with_plot / base:.2f}, the figure {cost[name]:.2f} s"
        )
    if "baseline" in cost:
        print(f"figure cost this / baseline = {cost['this'] / cost['baseline']:.3f}")
    print(f"load {load}")


if __name__ == "__main__":
    main()
