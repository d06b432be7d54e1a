"""Benchmark: ``imufdi calibrate``'s peak memory and time on a log and on one 10x longer.

Target: peak memory on the 10x longer log at most 1.3x the base log's (calibrate streams
the log in passes: static intervals, interval means and gyro sums, noise and time
offsets, jitter; its per-row values go to temporary files, not to memory).

The base log is the bundled real cut (``imufdi_cli/sample_logs/mimu4444-exp1-cut.bin``: 300 s of an
8-IMU board at 62.5 Hz, 10 static orientations and 45 s of hand motion) ingested with its
layout and array; the long one repeats its samples ``--factor`` times end to end (10
times the orientations, the motion and the clipped rows), written at run time. Each run is
a fresh ``python -m imufdi_cli calibrate`` subprocess: peak RSS is its ``ru_maxrss``
(``wait4``), time its wall clock; ``--repeat`` runs, the best kept. The load average is
printed: on a shared machine only the ratios mean something.

    python benchmarks/bench_calibrate.py              # 10x
    python benchmarks/bench_calibrate.py --factor 3   # quicker
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SAMPLES = REPO / "imufdi_cli" / "sample_logs"


def _imufdi(*args: object) -> None:
    subprocess.run(
        [sys.executable, "-m", "imufdi_cli", *map(str, args), "-q"],
        check=True,
        env=dict(os.environ, PYTHONPATH=str(REPO)),
    )


def _repeat(source: Path, target: Path, factor: int) -> None:
    """``source``'s samples ``factor`` times end to end, in blocks (bounded memory)."""
    sys.path.insert(0, str(REPO))
    from imufdi_cli.mcapio import ImuArrayReader, ImuArrayWriter, McapSource, McapWriter

    with McapSource(source) as src:
        metadata = {k: v for k, v in src.metadata.items() if k != "imufdi.array"}
    with ImuArrayReader(source) as reader:
        array = reader.array
        first = last = None
        period = None
        for block in reader.blocks():
            first = int(block.t_ns[0]) if first is None else first
            if period is None and len(block) > 1:
                period = int(block.t_ns[1] - block.t_ns[0])
            last = int(block.t_ns[-1])
    assert first is not None and last is not None and period is not None
    span = last - first + period
    with McapWriter(target) as writer:
        out = ImuArrayWriter(writer, array)
        for name, values in metadata.items():
            writer.add_metadata(name, values)
        for k in range(factor):
            with ImuArrayReader(source) as reader:
                for block in reader.blocks():
                    block.t_ns = block.t_ns + k * span
                    out.write_block(block)


def _measure(log: Path, out: Path) -> tuple[float, float]:
    """(seconds, peak RSS in MB) of one calibrate run in a fresh process."""
    started = time.monotonic()
    process = subprocess.Popen(
        [sys.executable, "-m", "imufdi_cli", "calibrate", str(log), "-o", str(out), "-q"],
        env=dict(os.environ, PYTHONPATH=str(REPO)),
    )
    _, status, usage = os.wait4(process.pid, 0)
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"calibrate {log} failed")
    return time.monotonic() - started, usage.ru_maxrss / 1024


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--factor", type=int, default=10, help="length of the long log")
    parser.add_argument("--repeat", type=int, default=2, help="runs of each, best kept")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="imufdi-bench-calibrate-") as tmp:
        work = Path(tmp)
        base = work / "cut.mcap"
        _imufdi(
            "ingest",
            SAMPLES / "mimu4444-exp1-cut.bin",
            "--layout",
            REPO / "docs/layouts/mimu4444.toml",
            "--array",
            SAMPLES / "mimu4444-array.toml",
            "-o",
            base,
        )
        long = work / "long.mcap"
        _repeat(base, long, args.factor)
        print(f"load average {os.getloadavg()[0]:.2f} (2 cores)")
        figures = {}
        for name, log in (("base", base), (f"{args.factor}x", long)):
            runs = [_measure(log, work / f"{name}.toml") for _ in range(args.repeat)]
            seconds = min(r[0] for r in runs)
            rss = min(r[1] for r in runs)
            figures[name] = (seconds, rss)
            size = log.stat().st_size / 2**20
            print(
                f"calibrate {name:>4}: {size:7.1f} MiB log, {seconds:6.2f} s, peak RSS {rss:6.1f} MB"
            )
        (s0, m0), (s1, m1) = figures["base"], figures[f"{args.factor}x"]
        ratio = m1 / m0
        print(
            f"peak memory {args.factor}x / base: {ratio:.3f} (target <= 1.3:"
            f" {'met' if ratio <= 1.3 else 'MISSED'}); time {args.factor}x / base: {s1 / s0:.2f}"
        )


if __name__ == "__main__":
    main()
