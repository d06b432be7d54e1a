"""Ingest throughput and memory on a capture shaped like a real board's.

The capture is made at run time by simulate (16 IMUs at 100 Hz, turntable motion, the
built-in ``mpu6500-array`` layout at 500 dps / 4 g, a few corrupted stretches per block:
garbage, flipped bits, a cut frame), the same path as ``imufdi simulate --capture``. Then

- parse only (MB/s of capture),
- parse + MCAP write through ``imufdi_cli.capture.ingest`` (MB/s of capture; issue 20
  target >= 40), with the process CPU time, so a loaded machine can be told from a slow
  ingest,
- peak traced memory (tracemalloc) of the ingest for a capture of size S and 4 S: the
  ratio should stay near 1 (streaming, memory flat in capture size).

Prints the load average before and after: the machine is often shared.

Usage: python benchmarks/bench_ingest.py [--minutes 20] [--imus 16] [--memory-minutes 2]
"""

from __future__ import annotations

import argparse
import gc
import os
import tempfile
import time
import tracemalloc
from pathlib import Path

from imufdi_cli.capture import CaptureEncoder, Corruption, ingest, load_layout, parse_capture


def make_capture(path: Path, minutes: float, n_imus: int = 16, seed: int = 1) -> int:
    """Simulate ``minutes`` of a 100 Hz array and write its mpu6500-array capture."""
    from imufdi_cli.simulate import config_from_options, simulate

    config = config_from_options(
        None,
        seed=seed,
        imus=n_imus,
        rate="100Hz",
        duration=f"{minutes * 60}s",
        motion="turntable",
    )
    array, blocks = simulate(config)
    encoder = CaptureEncoder(array, corrupt=Corruption(garbage=2, flipped=2, cut=1), seed=seed)
    with path.open("wb") as handle:
        for block in blocks:
            handle.write(encoder.encode(block))
        handle.write(encoder.finish())
    return path.stat().st_size


def parse_only(path: Path) -> float:
    layout = load_layout("mpu6500-array")
    start = time.perf_counter()
    blocks, _ = parse_capture(path, layout)
    for _ in blocks:
        pass
    return time.perf_counter() - start


def ingest_once(path: Path, out: Path, *, trace: bool) -> tuple[float, float, int]:
    """(wall s, process CPU s, peak traced bytes) of one ingest."""
    layout = load_layout("mpu6500-array")
    out.unlink(missing_ok=True)  # replacing a large file costs its unlink: not ingest's work
    gc.collect()
    if trace:
        tracemalloc.start()
    start = time.perf_counter()
    cpu = time.process_time()
    ingest(path, out, layout=layout, array=None)
    elapsed = time.perf_counter() - start
    cpu = time.process_time() - cpu
    peak = 0
    if trace:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return elapsed, cpu, peak


def load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=20.0, help="capture length")
    parser.add_argument("--imus", type=int, default=16)
    parser.add_argument("--memory-minutes", type=float, default=2.0, help="base for memory")
    parser.add_argument("--repeat", type=int, default=2, help="ingest runs (best is shown)")
    args = parser.parse_args()
    from imufdi_cli.mcapio.compression import CRC32_IMPLEMENTATION

    print(f"load average before: {load()} ({os.cpu_count()} cores)")
    print(f"chunk CRC-32 by {CRC32_IMPLEMENTATION}")
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        big = root / "big.cap"
        size = make_capture(big, args.minutes, args.imus)
        mb = size / 1e6
        t_parse = min(parse_only(big) for _ in range(args.repeat))
        runs = [ingest_once(big, root / "big.mcap", trace=False) for _ in range(args.repeat)]
        t_ingest, cpu, _ = min(runs)
        out_mb = (root / "big.mcap").stat().st_size / 1e6
        print(
            f"capture: {mb:.1f} MB, {args.imus} IMUs, 100 Hz, {args.minutes:g} min,"
            f" mpu6500-array (simulate, corrupted stretches); MCAP {out_mb:.1f} MB"
        )
        print(f"parse only      : {t_parse:6.2f} s  {mb / t_parse:7.1f} MB/s")
        print(
            f"parse + MCAP    : {t_ingest:6.2f} s  {mb / t_ingest:7.1f} MB/s  (target >= 40)"
            f"  CPU {cpu:.2f} s ({mb / cpu:.1f} MB per CPU-second)"
        )
        print(f"MCAP share      : {1 - t_parse / t_ingest:6.1%} of ingest time")
        peaks = []
        for factor in (1, 4):
            path = root / f"mem{factor}.cap"
            size = make_capture(path, args.memory_minutes * factor, args.imus)
            _, _, peak = ingest_once(path, root / f"mem{factor}.mcap", trace=True)
            peaks.append(peak)
            print(f"peak memory, {size / 1e6:6.1f} MB capture: {peak / 1e6:7.1f} MB")
        print(f"peak memory ratio 4x / 1x: {peaks[1] / peaks[0]:.2f} (flat = 1.0)")
    print(f"load average after: {load()}")


if __name__ == "__main__":
    main()
