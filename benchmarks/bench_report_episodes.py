"""What the explained episodes add to ``imufdi report``'s time (issue 22: at most 10 %).

Usage::

    python benchmarks/bench_report_episodes.py [--preset paper-table4] [--minutes 10]
        [--detectors glt] [--repeat 5] [--seed 17999]

Simulates the preset, injects a 0.9 deg/s step and a x3 noise growth (20 s each), runs
``imufdi detect`` once with the explanations (the default) and once with ``--no-explain``
on the same log, then runs ``imufdi report LOG -q`` on the two outputs alternately, each
in a fresh process, ``--repeat`` times. Prints each output's episode count, the CPU time
(user + system of the child) and wall time of every report, and the ratio explained /
unexplained of the best and of the median CPU times, with the load average. The
unexplained output is the same log without the ``episode`` events: the difference is what
reading, decoding and scoring the episodes costs the report.

The default (paper-table4, glt at its 1 % level) is the alarm-heavy case: about two
false episodes a second. With ``--detectors pca-parity,noise-glr`` episodes are few.
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

ENV = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}


def imufdi(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "imufdi_cli", *args], check=True, env=ENV)


def timed_report(path: Path) -> tuple[float, float]:
    """(CPU seconds, wall seconds) of ``imufdi report path -q`` in a fresh process."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    subprocess.run(
        [sys.executable, "-m", "imufdi_cli", "report", str(path), "-q"],
        check=True,
        env=ENV,
        stdout=subprocess.DEVNULL,
    )
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return cpu, wall


def episode_count(path: Path) -> int:
    from imufdi_cli.mcapio import read_events

    return sum(1 for _, e in read_events(str(path), "/imufdi/events") if e["event"] == "episode")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--preset", default="paper-table4")
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--detectors", default="glt")
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--seed", type=int, default=17999)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        log, faulty = work / "log.mcap", work / "faulty.mcap"
        imufdi(
            "simulate", "--preset", args.preset, "--duration", f"{args.minutes * 60:g}s",
            "--seed", str(args.seed), "-o", str(log), "-q",
        )  # fmt: skip
        third = args.minutes * 60 / 3
        imufdi(
            "inject", str(log), "-o", str(faulty), "-q",
            "--fault", f"step:imu3.gyro.x,at={third:.1f}s,duration=20s,amp=0.9deg/s",
            "--fault", f"noise:imu7.gyro.y,at={2 * third:.1f}s,duration=20s,factor=3",
        )  # fmt: skip
        outputs = {"explained": work / "explained.mcap", "unexplained": work / "plain.mcap"}
        dets = [x for d in args.detectors.split(",") for x in ("-d", d)]
        imufdi("detect", str(faulty), *dets, "-o", str(outputs["explained"]), "-q")
        imufdi(
            "detect", str(faulty), *dets, "--no-explain", "-o", str(outputs["unexplained"]), "-q"
        )
        for name, path in outputs.items():
            print(f"{name}: {episode_count(path)} episodes, {path.stat().st_size / 1e6:.1f} MB")
        times: dict[str, list[tuple[float, float]]] = {name: [] for name in outputs}
        for _ in range(args.repeat):
            for name, path in outputs.items():
                times[name].append(timed_report(path))
        for name, runs in times.items():
            print(
                f"report {name}: CPU "
                + " ".join(f"{c:.2f}" for c, _ in runs)
                + " s; wall "
                + " ".join(f"{w:.2f}" for _, w in runs)
                + " s"
            )
        cpu = {name: [c for c, _ in runs] for name, runs in times.items()}
        best = min(cpu["explained"]) / min(cpu["unexplained"])
        median = statistics.median(cpu["explained"]) / statistics.median(cpu["unexplained"])
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    print(
        f"{args.preset}, {args.minutes:g} min, -d {args.detectors}: report CPU explained /"
        f" unexplained {best:.3f}x (best of {args.repeat}), {median:.3f}x (medians);"
        f" target <= 1.10x; load average {load}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
