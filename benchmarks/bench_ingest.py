"""Ingest throughput and memory: parse a large mpu6500-array capture and write MCAP.

Generates the capture at run time (16 IMUs, a few corrupted stretches), then measures

- parse only (MB/s of capture),
- parse + MCAP write through ``imufdi_cli.capture.ingest`` (MB/s; target >= 30),
- peak traced memory (tracemalloc) of the ingest for a capture of size S and 4 S: the
  ratio should stay near 1 (streaming, memory flat in capture size).

Usage: python benchmarks/bench_ingest.py [--mb 100]
"""

from __future__ import annotations

import argparse
import gc
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

from imufdi_cli.capture import CaptureEncoder, Corruption, ingest, load_layout, parse_capture
from imufdi_cli.log import ImuBlock


def make_capture(path: Path, megabytes: float, n_imus: int = 16) -> int:
    layout = load_layout("mpu6500-array")
    frame = layout.frame_size(n_imus)
    n_frames = int(megabytes * 1e6 / frame)
    rng = np.random.default_rng(0)
    encoder = CaptureEncoder(layout=layout, corrupt=Corruption(garbage=2, flipped=2, cut=1), seed=1)
    block_size = 20_000
    with path.open("wb") as handle:
        for start in range(0, n_frames, block_size):
            n = min(block_size, n_frames - start)
            t_ns = (start + np.arange(n, dtype=np.int64)) * 1_000_000  # 1 kHz
            block = ImuBlock(
                t_ns=t_ns,
                gyro=rng.normal(0.0, 0.5, (n, n_imus, 3)),
                accel=rng.normal(0.0, 5.0, (n, n_imus, 3)),
            )
            handle.write(encoder.encode(block))
    return path.stat().st_size


def parse_only(path: Path) -> float:
    layout = load_layout("mpu6500-array")
    start = time.perf_counter()
    blocks, _ = parse_capture(path, layout)
    for _ in blocks:
        pass
    return time.perf_counter() - start


def ingest_once(path: Path, out: Path, *, trace: bool) -> tuple[float, int]:
    layout = load_layout("mpu6500-array")
    gc.collect()
    if trace:
        tracemalloc.start()
    start = time.perf_counter()
    ingest(path, out, layout=layout, array=None)
    elapsed = time.perf_counter() - start
    peak = 0
    if trace:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return elapsed, peak


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--mb", type=float, default=100.0, help="capture size for throughput")
    parser.add_argument("--memory-mb", type=float, default=10.0, help="base size for memory")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        big = root / "big.cap"
        size = make_capture(big, args.mb)
        mb = size / 1e6
        t_parse = parse_only(big)
        t_ingest, _ = ingest_once(big, root / "big.mcap", trace=False)
        print(f"capture: {mb:.1f} MB, 16 IMUs, mpu6500-array")
        print(f"parse only      : {t_parse:6.2f} s  {mb / t_parse:7.1f} MB/s")
        print(f"parse + MCAP    : {t_ingest:6.2f} s  {mb / t_ingest:7.1f} MB/s  (target >= 30)")
        print(f"MCAP share      : {1 - t_parse / t_ingest:6.1%} of ingest time")
        peaks = []
        for factor in (1, 4):
            path = root / f"mem{factor}.cap"
            size = make_capture(path, args.memory_mb * factor)
            _, peak = ingest_once(path, root / f"mem{factor}.mcap", trace=True)
            peaks.append(peak)
            print(f"peak memory, {size / 1e6:6.1f} MB capture: {peak / 1e6:7.1f} MB")
        print(f"peak memory ratio 4x / 1x: {peaks[1] / peaks[0]:.2f} (flat = 1.0)")


if __name__ == "__main__":
    main()
