"""What the explained episodes add to ``imufdi report``'s time (target: at most 10 %).

Usage::

    python benchmarks/bench_report_episodes.py [--preset paper-table4] [--minutes 10]
        [--detectors glt] [--repeat 5] [--seed 17999] [--baseline DIR]

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

``--baseline DIR`` (a directory holding another version's ``imufdi_cli``, e.g. an export
of main) also runs detect and report of that version on the same faulty log, its four
reports alternated with these in the same loop, and prints its ratio too.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from bench_plot import timed  # CPU and wall of a fresh imufdi process

ENV = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}


def _env(tree: str | None) -> dict[str, str]:
    """The environment of a child running the ``imufdi_cli`` in ``tree`` (None: this
    one's, as found on the current path)."""
    if tree is None:
        return ENV
    return {**ENV, "PYTHONPATH": os.path.abspath(tree)}


def imufdi(*args: str, tree: str | None = None) -> None:
    # from the tree itself: ``-m`` puts the working directory first on the path
    subprocess.run(
        [sys.executable, "-m", "imufdi_cli", *args], check=True, env=_env(tree), cwd=tree
    )


def timed_report(path: Path, tree: str | None = None) -> tuple[float, float]:
    """(CPU seconds, wall seconds) of ``imufdi report path -q`` in a fresh process."""
    return timed(["report", str(path), "-q"], tree)


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
    parser.add_argument("--baseline", default=None, help="another version's source tree")
    args = parser.parse_args()
    if args.baseline is not None and not os.path.isdir(os.path.join(args.baseline, "imufdi_cli")):
        parser.error(f"--baseline {args.baseline}: no imufdi_cli directory there")
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
        versions = {"": None} if args.baseline is None else {"": None, "baseline ": args.baseline}
        outputs: dict[str, tuple[Path, str | None]] = {}
        dets = [x for d in args.detectors.split(",") for x in ("-d", d)]
        for prefix, tree in versions.items():
            tag = prefix.strip() or "this"
            explained, plain = work / f"{tag}-explained.mcap", work / f"{tag}-plain.mcap"
            imufdi("detect", str(faulty), *dets, "-o", str(explained), "-q", tree=tree)
            imufdi("detect", str(faulty), *dets, "--no-explain", "-o", str(plain), "-q", tree=tree)
            outputs[f"{prefix}explained"] = (explained, tree)
            outputs[f"{prefix}unexplained"] = (plain, tree)
        for name, (path, _) in outputs.items():
            print(f"{name}: {episode_count(path)} episodes, {path.stat().st_size / 1e6:.1f} MB")
        times: dict[str, list[tuple[float, float]]] = {name: [] for name in outputs}
        for _ in range(args.repeat):
            for name, (path, tree) in outputs.items():
                times[name].append(timed_report(path, tree))
        for name, runs in times.items():
            print(
                f"report {name}: CPU "
                + " ".join(f"{c:.2f}" for c, _ in runs)
                + " s; wall "
                + " ".join(f"{w:.2f}" for _, w in runs)
                + " s"
            )
        cpu = {name: [c for c, _ in runs] for name, runs in times.items()}
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    for prefix in versions:
        explained, plain = cpu[f"{prefix}explained"], cpu[f"{prefix}unexplained"]
        best = min(explained) / min(plain)
        median = statistics.median(explained) / statistics.median(plain)
        print(
            f"{prefix or 'this version '}{args.preset}, {args.minutes:g} min, -d"
            f" {args.detectors}: report CPU explained / unexplained {best:.3f}x (best of"
            f" {args.repeat}), {median:.3f}x (medians); target <= 1.10x; load average {load}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
