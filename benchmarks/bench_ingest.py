"""Ingest throughput and memory on a capture shaped like a real board's.

The capture is made at run time by simulate (16 IMUs at 100 Hz, turntable motion, the
built-in ``mpu6500-array`` layout at 500 dps / 4 g, a few corrupted stretches per block:
garbage, flipped bits, a cut frame), the same path as ``imufdi simulate --capture``. Then

- parse only (MB/s of capture; CPU of the calling thread),
- parse + MCAP write through ``imufdi_cli.capture.ingest`` (MB/s of capture;
  target >= 40), with the process CPU time and the calling thread's CPU time, so a loaded
  machine can be told from a slow ingest,
- the baseline, measured in the same run on the same records: the chunk compression
  alone (the writer's zstd level and the CRC-32 of every chunk of the ingest's output,
  re-compressed on one thread; any writer of these bytes pays it), the same on two
  threads (every core compressing and nothing else: a bound no ingest reaches), and the
  ratios of ingest to them,
- ``--pairs`` ingests each followed by one pass of the one-thread baseline, and the
  median and range of the per-pair ratios (wall and CPU): the figure to quote on a shared
  machine, where the load changes between the best-of runs,
- the bound the CPU figures give with two free cores:
  ``capture / max(calling thread CPU, process CPU / 2)``,
- peak traced memory (tracemalloc) of the ingest for a capture of size S and 4 S: the
  ratio should stay near 1 (streaming, memory flat in capture size),
- with ``--settings``: CPU and output size of the chunk compression at other zstd levels
  and chunk sizes (and lz4) on the same records.

Prints the load average before and after: the machine is often shared.

Usage: python benchmarks/bench_ingest.py [--minutes 20] [--imus 16] [--repeat 3]
       [--pairs 5] [--memory-minutes 2] [--skip-memory] [--settings]
"""

from __future__ import annotations

import argparse
import gc
import os
import statistics
import struct
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


def parse_only(path: Path) -> tuple[float, float]:
    """(wall s, calling thread CPU s) of parsing the whole capture."""
    layout = load_layout("mpu6500-array")
    start = time.perf_counter()
    cpu = time.thread_time()
    blocks, _ = parse_capture(path, layout)
    for _ in blocks:
        pass
    return time.perf_counter() - start, time.thread_time() - cpu


def ingest_once(path: Path, out: Path, *, trace: bool) -> tuple[float, float, float, int]:
    """(wall s, process CPU s, calling thread CPU s, peak traced bytes) of one ingest."""
    layout = load_layout("mpu6500-array")
    out.unlink(missing_ok=True)  # replacing a large file costs its unlink: not ingest's work
    gc.collect()
    if trace:
        tracemalloc.start()
    start = time.perf_counter()
    cpu = time.process_time()
    main = time.thread_time()
    ingest(path, out, layout=layout, array=None)
    elapsed = time.perf_counter() - start
    cpu = time.process_time() - cpu
    main = time.thread_time() - main
    peak = 0
    if trace:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return elapsed, cpu, main, peak


def chunk_records(path: Path) -> list[bytes]:
    """The uncompressed records of every chunk of an MCAP file, in file order."""
    from imufdi_cli.mcapio.compression import decompress

    raw = path.read_bytes()
    chunks = []
    position = 8
    while position + 9 <= len(raw):
        opcode, length = struct.unpack_from("<BQ", raw, position)
        if opcode == 0x06:  # Chunk
            content = memoryview(raw)[position + 9 : position + 9 + length]
            uncompressed = struct.unpack_from("<Q", content, 16)[0]
            name_length = struct.unpack_from("<I", content, 28)[0]
            name = bytes(content[32 : 32 + name_length]).decode()
            records_at = 32 + name_length + 8
            chunks.append(decompress(content[records_at:], name, uncompressed))
        elif opcode == 0x0F:  # DataEnd
            break
        position += 9 + length
    return chunks


def time_compression(chunks: list[bytes], compress, repeat: int = 3) -> tuple[float, float, int]:
    """(wall s, CPU s, output bytes) of ``compress`` plus the CRC-32 of every chunk on
    one thread (best of ``repeat``)."""
    from imufdi_cli.mcapio.compression import crc32

    best = (float("inf"), float("inf"), 0)
    for _ in range(repeat):
        start = time.perf_counter()
        cpu = time.thread_time()
        size = 0
        for records in chunks:
            crc32(records)
            size += len(compress(records))
        best = min(best, (time.perf_counter() - start, time.thread_time() - cpu, size))
    return best


def time_compression_threads(chunks: list[bytes], threads: int = 2, repeat: int = 3) -> float:
    """Wall s of the zstd compression and CRC-32 of every chunk on ``threads`` threads
    (zstandard and the CRC release the GIL), best of ``repeat``: what the chunks cost
    with every core compressing and nothing else to do."""
    from concurrent.futures import ThreadPoolExecutor

    from imufdi_cli.mcapio.compression import compress, crc32

    def one(records: bytes) -> int:
        crc32(records)
        return len(compress(records, "zstd"))

    best = float("inf")
    with ThreadPoolExecutor(threads) as pool:
        list(pool.map(one, chunks[:threads]))  # threads started, compressors made
        for _ in range(repeat):
            start = time.perf_counter()
            sum(pool.map(one, chunks))
            best = min(best, time.perf_counter() - start)
    return best


def rechunk(chunks: list[bytes], chunk_size: int) -> list[bytes]:
    """The same records cut into chunks of about ``chunk_size`` bytes (whole records of
    the first chunk's record size; the ingest's records all have one size)."""
    joined = b"".join(chunks)
    record = struct.unpack_from("<Q", joined, 1)[0] + 9
    step = max(1, -(-chunk_size // record)) * record
    return [joined[i : i + step] for i in range(0, len(joined), step)]


def settings_table(chunks: list[bytes], mb: float) -> None:
    """CPU and output size of other chunk compression settings on the same records."""
    import lz4.frame
    import zstandard

    from imufdi_cli.mcapio.compression import ZSTD_LEVEL

    print("chunk compression settings (same records, one thread, CRC-32 included):")
    print("  compression        chunk   CPU s  MB capture/CPU-s  compressed MB")
    for size in (4 << 20, 1 << 20, 256 << 10):
        cut = rechunk(chunks, size)
        for level in (ZSTD_LEVEL, 1, -1, -5, -7):
            compressor = zstandard.ZstdCompressor(level=level, write_checksum=True)
            _, cpu, out = time_compression(cut, compressor.compress, repeat=2)
            label = f"zstd {level}" + (" (writer)" if level == ZSTD_LEVEL else "")
            print(f"  {label:17s} {size >> 10:5d}K {cpu:7.3f} {mb / cpu:12.1f} {out / 1e6:14.2f}")
        _, cpu, out = time_compression(
            cut, lambda r: lz4.frame.compress(r, content_checksum=True), repeat=2
        )
        print(f"  {'lz4':17s} {size >> 10:5d}K {cpu:7.3f} {mb / cpu:12.1f} {out / 1e6:14.2f}")


def load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=20.0, help="capture length")
    parser.add_argument("--imus", type=int, default=16)
    parser.add_argument("--memory-minutes", type=float, default=2.0, help="base for memory")
    parser.add_argument("--repeat", type=int, default=3, help="runs of each (best is shown)")
    parser.add_argument(
        "--pairs", type=int, default=5, help="ingest / baseline pairs, alternated (median shown)"
    )
    parser.add_argument("--skip-memory", action="store_true", help="no memory measurement")
    parser.add_argument(
        "--settings", action="store_true", help="also other zstd levels, chunk sizes, lz4"
    )
    args = parser.parse_args()
    from imufdi_cli.mcapio.compression import CRC32_IMPLEMENTATION, ZSTD_LEVEL, compress

    print(f"load average before: {load()} ({os.cpu_count()} cores)")
    print(f"chunk CRC-32 by {CRC32_IMPLEMENTATION}, zstd level {ZSTD_LEVEL}")
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        big = root / "big.cap"
        size = make_capture(big, args.minutes, args.imus)
        mb = size / 1e6
        # a first ingest pays the imports and the threads' start: not counted
        ingest_once(big, root / "big.mcap", trace=False)
        t_parse, cpu_parse = min(parse_only(big) for _ in range(args.repeat))
        runs = [ingest_once(big, root / "big.mcap", trace=False) for _ in range(args.repeat)]
        t_ingest, cpu, main_cpu, _ = min(runs)
        out_mb = (root / "big.mcap").stat().st_size / 1e6
        chunks = chunk_records(root / "big.mcap")
        records_mb = sum(len(c) for c in chunks) / 1e6
        t_floor, cpu_floor, _ = time_compression(chunks, lambda r: compress(r, "zstd"))
        t_floor2 = time_compression_threads(chunks, 2)
        # ingest and the one-thread baseline alternated: each pair is measured within a
        # few seconds, so a change of load moves both (the best-of figures above do not)
        pairs = []
        for _ in range(args.pairs):
            wall, cpu_run, _, _ = ingest_once(big, root / "big.mcap", trace=False)
            wall_floor, cpu_floor_run, _ = time_compression(
                chunks, lambda r: compress(r, "zstd"), repeat=1
            )
            pairs.append((wall / wall_floor, cpu_run / cpu_floor_run))
        print(
            f"capture: {mb:.1f} MB, {args.imus} IMUs, 100 Hz, {args.minutes:g} min,"
            f" mpu6500-array (simulate, corrupted stretches); MCAP {out_mb:.1f} MB"
            f" ({records_mb:.0f} MB of records in {len(chunks)} chunks)"
        )
        print(
            f"parse only      : {t_parse:6.3f} s  {mb / t_parse:7.1f} MB/s"
            f"  CPU {cpu_parse:.3f} s ({mb / cpu_parse:.1f} MB per CPU-second)"
        )
        print(
            f"parse + MCAP    : {t_ingest:6.3f} s  {mb / t_ingest:7.1f} MB/s  (target >= 40)"
            f"  CPU {cpu:.3f} s ({mb / cpu:.1f} MB per CPU-second),"
            f" calling thread {main_cpu:.3f} s"
        )
        print(
            f"baseline        : {t_floor:6.3f} s  {mb / t_floor:7.1f} MB/s"
            f"  CPU {cpu_floor:.3f} s: zstd {ZSTD_LEVEL} + CRC-32 of the same chunks, one thread"
        )
        print(
            f"baseline, 2 thr : {t_floor2:6.3f} s  {mb / t_floor2:7.1f} MB/s"
            f"  the same on two threads (all the cores compressing, nothing else)"
        )
        print(
            f"ingest / baseline: {t_ingest / t_floor:.2f}x wall, {cpu / cpu_floor:.2f}x CPU"
            f" (the compression is {cpu_floor / cpu:.0%} of ingest's CPU);"
            f" ingest MB/s = {t_floor / t_ingest:.0%} of the one-thread baseline's,"
            f" {t_floor2 / t_ingest:.0%} of the two-thread one's"
        )
        if pairs:
            walls = sorted(w for w, _ in pairs)
            cpus = sorted(c for _, c in pairs)
            print(
                f"paired runs ({len(pairs)}): ingest / baseline median {statistics.median(walls):.2f}x"
                f" wall (range {walls[0]:.2f}-{walls[-1]:.2f}),"
                f" {statistics.median(cpus):.2f}x CPU (range {cpus[0]:.2f}-{cpus[-1]:.2f})"
            )
        bound = mb / max(main_cpu, cpu / 2)
        print(
            f"two free cores  : at most {bound:.1f} MB/s"
            f" (capture / max(calling thread CPU, CPU / 2))"
        )
        if args.settings:
            settings_table(chunks, mb)
        if not args.skip_memory:
            peaks = []
            for factor in (1, 4):
                path = root / f"mem{factor}.cap"
                size = make_capture(path, args.memory_minutes * factor, args.imus)
                peak = ingest_once(path, root / f"mem{factor}.mcap", trace=True)[3]
                peaks.append(peak)
                print(f"peak memory, {size / 1e6:6.1f} MB capture: {peak / 1e6:7.1f} MB")
            print(f"peak memory ratio 4x / 1x: {peaks[1] / peaks[0]:.2f} (flat = 1.0)")
    print(f"load average after: {load()}")


if __name__ == "__main__":
    main()
