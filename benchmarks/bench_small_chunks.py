"""Benchmark: the reader's cost per chunk, and the cost of checking chunk CRCs.

Usage: python benchmarks/bench_small_chunks.py [--imus 16] [--samples 500] [--repeat 3]

Writes one log (imus x samples sensor_msgs/msg/Imu messages, the paper-table4 size by
default) twice, with the writer's 1 MiB chunks and with 100-byte chunks (one message per
chunk), and times ``summarize`` (what ``imufdi info`` does: read, decode, align) on both,
best of ``--repeat``. Prints the ratio small/large (36x before the reader joined small
chunks into 1 MiB batches), and the ratio of ``summarize`` with chunk CRCs
checked to without (``summarize(path, validate_crcs=False)``), on the large-chunk log
written uncompressed (so the ratio is the CRC's share of reading, not the decompression's).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from imufdi_cli.array import ArrayConfig
from imufdi_cli.log import ImuBlock
from imufdi_cli.mcapio import McapSource, McapWriter, summarize, write_array


def make_logs(directory: Path, n_imus: int, n_samples: int) -> tuple[Path, Path, Path]:
    rng = np.random.default_rng(0)
    block = ImuBlock(
        t_ns=np.arange(n_samples, dtype=np.int64) * 10_000_000 + 1_700_000_000 * 10**9,
        gyro=rng.normal(0, 0.01, (n_samples, n_imus, 3)),
        accel=rng.normal(0, 0.1, (n_samples, n_imus, 3)),
    )
    large = directory / "large-chunks.mcap"
    write_array(large, ArrayConfig.co_aligned(n_imus, 100.0), block)
    with_crc = directory / "large-chunks-none.mcap"
    write_array(with_crc, ArrayConfig.co_aligned(n_imus, 100.0), block, compression="none")
    small = directory / "small-chunks.mcap"
    with McapSource(large) as source, McapWriter(small, chunk_size=100) as writer:
        writer.copy_channels(source.channels)
        for name, values in source.metadata.items():
            writer.add_metadata(name, values)
        for batch in source.batches():
            writer.add_batch(batch)
    return large, small, with_crc


def best_time(path: Path, repeat: int, validate_crcs: bool = True) -> float:
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        summarize(path, validate_crcs=validate_crcs)
        times.append(time.perf_counter() - start)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--imus", type=int, default=16)
    parser.add_argument("--samples", type=int, default=500)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        large, small, with_crc = make_logs(Path(tmp), args.imus, args.samples)
        n_chunks = sum(1 for _ in McapSource(small).batches())
        t_large = best_time(large, args.repeat)
        t_small = best_time(small, args.repeat)
        t_crc = best_time(with_crc, args.repeat)
        t_no_crc = best_time(with_crc, args.repeat, validate_crcs=False)
    messages = args.imus * args.samples
    print(f"{messages} messages; small-chunk log read as {n_chunks} batches")
    print(f"summarize, 1 MiB chunks:   {t_large * 1e3:8.1f} ms")
    print(f"summarize, 100-byte chunks:{t_small * 1e3:8.1f} ms  ratio {t_small / t_large:.2f}")
    print(
        f"uncompressed, CRCs on/off: {t_crc * 1e3:8.1f} / {t_no_crc * 1e3:.1f} ms"
        f"  CRC cost ratio {t_crc / t_no_crc:.3f}"
    )


if __name__ == "__main__":
    main()
