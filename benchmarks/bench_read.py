"""Benchmark of imufdi's MCAP reader and writer against mcap-ros2-support, same run.

Usage: python benchmarks/bench_read.py [--imus 16] [--samples 62500] [--skip-memory]
       [--log FILE]

With ``--log`` the read timings (reader, floors, mcap-ros2-support) are made on that file
instead of a generated one (e.g. ``imufdi simulate --imus 16 --duration 10min -o x.mcap``);
the writer and memory lines then still use a generated log.

Makes a log of imus x samples sensor_msgs/msg/Imu messages in a temporary directory, then
- times ImuArrayWriter (bulk CDR encoding + zstd chunks) writing it,
- times ImuArrayReader.blocks() (all messages decoded and aligned; with the reader's
  default settings (in line unless IMUFDI_READ_AHEAD=1), then also explicitly in line
  and with read-ahead, each with the CPU of all threads and of the calling thread) and
  mcap_ros2's make_reader(..., decoder_factories=[DecoderFactory()]).iter_decoded_messages()
  on the same file (the latter on a subset of messages if --baseline-fraction < 1, rate
  extrapolated), prints messages/s and the ratio,
- times the floor on the same file: zstd decompression of every chunk plus one copy of its
  records (what any reader must at least do), and prints the reader's rate as a share of it
  (target: >= 50 %); also the floor with the CRC-32 of every chunk's records,
  which the reader verifies by default, and the reader with CRC checks off (the
  ImuArrayReader(path, validate_crcs=False)),
- with --malloc, times the in-line reader and the floor again in fresh processes, without
  and with glibc told to keep freed memory (MALLOC_MMAP_THRESHOLD_, MALLOC_TRIM_THRESHOLD_:
  what mallopt in the entry point would give; page faults cost about 4 us each here),
- measures peak memory (VmHWM of a fresh subprocess) reading the base log and a 10x
  longer log.
"""

from __future__ import annotations

import argparse
import os
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from imufdi_cli.array import ArrayConfig
from imufdi_cli.log import ImuBlock
from imufdi_cli.mcapio import ImuArrayReader, ImuArrayWriter, McapSource, McapWriter


def make_log(path: Path, n_imus: int, n_samples: int, block: int = 50_000) -> float:
    """Write the log block by block; returns the writer's wall time in seconds."""
    rng = np.random.default_rng(0)
    array = ArrayConfig.co_aligned(n_imus, 100.0)
    elapsed = 0.0
    with McapWriter(path) as writer:
        imu_writer = ImuArrayWriter(writer, array)
        for start in range(0, n_samples, block):
            n = min(block, n_samples - start)
            t_ns = (
                np.arange(start, start + n, dtype=np.int64) * 10_000_000
            ) + 1_700_000_000 * 10**9
            data = ImuBlock(
                t_ns=t_ns,
                gyro=rng.normal(0, 0.01, (n, n_imus, 3)),
                accel=rng.normal(0, 0.1, (n, n_imus, 3)) + np.array([0.0, 0.0, 9.81]),
            )
            t0 = time.perf_counter()
            imu_writer.write_block(data)
            elapsed += time.perf_counter() - t0
        t0 = time.perf_counter()
    elapsed += time.perf_counter() - t0  # close: last chunk + summary
    return elapsed


def time_imufdi(
    path: Path, validate_crcs: bool = True, read_ahead: bool | None = None
) -> tuple[float, int, float, float]:
    """(wall s, messages, CPU s of all threads, CPU s of the calling thread) of reading
    the whole log (decoded and aligned); ``read_ahead``: McapSource's (None: its default,
    in line unless IMUFDI_READ_AHEAD=1; True: a worker thread decompresses and reads the
    message heads and Imu fields; False: all in line)."""
    t0 = time.perf_counter()
    c0 = time.process_time()
    m0 = time.thread_time()
    n = 0
    source = McapSource(path, validate_crcs=validate_crcs, read_ahead=read_ahead)
    with ImuArrayReader(source) as reader:
        for block in reader.blocks():
            n += len(block) * block.n_imus
    return (
        time.perf_counter() - t0,
        n,
        time.process_time() - c0,
        time.thread_time() - m0,
    )


def time_floor(path: Path, crc: bool = False) -> tuple[float, float]:
    """(wall s, CPU s) to zstd-decompress every chunk of the file and copy its records
    once (best of three), on one thread; with ``crc``, also the CRC-32 of each chunk's
    records, by the reader's implementation (zlib-ng's when installed)."""
    import zstandard

    from imufdi_cli.mcapio.compression import crc32

    raw = path.read_bytes()
    chunks = []
    position = 8
    while position + 9 <= len(raw):
        opcode, length = struct.unpack_from("<BQ", raw, position)
        if opcode == 0x06:
            content = memoryview(raw)[position + 9 : position + 9 + length]
            uncompressed = struct.unpack_from("<Q", content, 16)[0]
            name_length = struct.unpack_from("<I", content, 28)[0]
            records_at = 32 + name_length + 8
            chunks.append((content[records_at:], uncompressed))
        elif opcode == 0x0F:  # DataEnd
            break
        position += 9 + length
    dctx = zstandard.ZstdDecompressor()
    best = (float("inf"), float("inf"))
    for _ in range(3):
        t0 = time.perf_counter()
        c0 = time.process_time()
        for data, size in chunks:
            records = dctx.decompress(data, max_output_size=size)
            np.frombuffer(records, np.uint8).copy()
            if crc:
                crc32(records)
        best = min(best, (time.perf_counter() - t0, time.process_time() - c0))
    return best


def time_mcap_ros2(path: Path, max_messages: int) -> tuple[float, int]:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    t0 = time.perf_counter()
    n = 0
    with open(path, "rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        for _, _, _, msg in reader.iter_decoded_messages():
            _ = (msg.angular_velocity.x, msg.linear_acceleration.z, msg.header.stamp.sec)
            n += 1
            if n >= max_messages:
                break
    return time.perf_counter() - t0, n


def peak_rss_reading(path: Path) -> int:
    """Peak resident memory (kB) of a fresh Python process reading the whole log: its
    VmHWM (Linux; ru_maxrss elsewhere). Not ru_maxrss on Linux: the kernel carries it over
    ``exec`` from the forked parent, so it reported this benchmark's own size (about
    165-180 MB after writing the 10x log) rather than the reader's."""
    code = (
        "import resource, sys\n"
        "from imufdi_cli.mcapio import ImuArrayReader\n"
        "n = 0\n"
        "with ImuArrayReader(sys.argv[1]) as r:\n"
        "    for b in r.blocks(): n += len(b)\n"
        "try:\n"
        "    status = open('/proc/self/status').read().split('VmHWM:')[1]\n"
        "    print(int(status.split()[0]))\n"
        "except (OSError, IndexError):\n"
        "    print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code, str(path)], check=True, capture_output=True, text=True
    )
    return int(out.stdout.strip().splitlines()[-1])


#: glibc settings under which freed memory is kept (no page faults for re-allocated
#: buffers): what ``mallopt`` in the entry point would give; see --malloc
KEEP_MEMORY = {"MALLOC_MMAP_THRESHOLD_": "268435456", "MALLOC_TRIM_THRESHOLD_": "1073741824"}


def time_in_process(path: Path, extra_env: dict[str, str]) -> tuple[float, float, float, float]:
    """(reader wall, reader CPU, floor wall, floor CPU), best of three each, in line,
    measured in a fresh process with ``extra_env`` added to its environment."""
    code = (
        "import sys\n"
        f"sys.path.insert(0, {str(Path(__file__).parent)!r})\n"
        "from pathlib import Path\n"
        "from bench_read import time_imufdi, time_floor\n"
        "p = Path(sys.argv[1])\n"
        "time_imufdi(p, read_ahead=False)\n"
        "w, _, c, _ = min(time_imufdi(p, read_ahead=False) for _ in range(3))\n"
        "fw, fc = time_floor(p)\n"
        "print(w, c, fw, fc)\n"
    )
    env = dict(os.environ, **extra_env)
    out = subprocess.run(
        [sys.executable, "-c", code, str(path)], check=True, capture_output=True, text=True, env=env
    )
    wall, cpu, floor_wall, floor_cpu = (float(x) for x in out.stdout.split()[-4:])
    return wall, cpu, floor_wall, floor_cpu


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--imus", type=int, default=16)
    parser.add_argument("--samples", type=int, default=62_500)
    parser.add_argument(
        "--baseline-messages",
        type=int,
        default=200_000,
        help="messages decoded by mcap-ros2-support (rate extrapolated; it is slow)",
    )
    parser.add_argument("--skip-memory", action="store_true")
    parser.add_argument(
        "--malloc",
        action="store_true",
        help="also time the in-line reader and the floor in fresh processes with and without"
        " glibc keeping freed memory (MALLOC_MMAP/TRIM_THRESHOLD_): the page faults' share",
    )
    parser.add_argument("--log", type=Path, help="MCAP to time the readers on (default: generated)")
    args = parser.parse_args()
    from imufdi_cli.mcapio.compression import CRC32_IMPLEMENTATION

    print(f"load average: {' '.join(f'{x:.2f}' for x in os.getloadavg())} ({os.cpu_count()} cores)")
    print(
        f"chunk CRC-32 by {CRC32_IMPLEMENTATION}; CPU is of all threads (the read-ahead"
        " line uses a second one)"
    )
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp) / "base.mcap"
        n_messages = args.imus * args.samples
        write_s = make_log(base, args.imus, args.samples)
        print(f"imufdi writer        : {write_s:7.2f} s  {n_messages / write_s:12,.0f} msg/s")
        generated = base
        if args.log is not None:
            base = args.log
            with ImuArrayReader(base) as probe:
                n_messages = sum(len(b) * b.n_imus for b in probe.blocks())
        size_mb = base.stat().st_size / 1e6
        print(f"log: {base.name}, {n_messages:,} Imu messages, {size_mb:.1f} MB")
        with McapSource(base) as probe_source:
            default_ahead = probe_source.read_ahead
        ours_s, ours_n, ours_cpu, ours_main = min(time_imufdi(base) for _ in range(3))
        assert ours_n == n_messages, (ours_n, n_messages)
        ours_rate = ours_n / ours_s
        print(
            f"imufdi reader        : {ours_s:7.2f} s  {ours_rate:12,.0f} msg/s (decoded+aligned;"
            f" default settings: read-ahead {'on' if default_ahead else 'off'}), CPU"
            f" {ours_cpu:.2f} s, calling thread {ours_main:.2f} s"
        )
        floor_s, floor_cpu = time_floor(base)
        print(
            f"zstd floor           : {floor_s:7.2f} s  {n_messages / floor_s:12,.0f} msg/s"
            f" (decompress + copy the same chunks), CPU {floor_cpu:.2f} s"
        )
        print(
            f"reader / floor       : {floor_s / ours_s:7.1%} wall, {floor_cpu / ours_cpu:.1%} CPU"
            f" (reader CPU {ours_cpu:.2f} s)  (target >= 50 %)"
        )
        crc_s, crc_cpu = time_floor(base, crc=True)
        print(
            f"zstd + CRC-32 floor  : {crc_s:7.2f} s  {n_messages / crc_s:12,.0f} msg/s"
            f" (as above, plus the CRC-32 the reader verifies), CPU {crc_cpu:.2f} s"
        )
        print(f"reader / CRC floor   : {crc_s / ours_s:7.1%} wall, {crc_cpu / ours_cpu:.1%} CPU")
        nocrc_s, nocrc_n, nocrc_cpu, _ = min(
            time_imufdi(base, validate_crcs=False) for _ in range(3)
        )
        assert nocrc_n == n_messages, (nocrc_n, n_messages)
        print(
            f"reader, CRCs off     : {nocrc_s:7.2f} s  {n_messages / nocrc_s:12,.0f} msg/s,"
            f" {floor_s / nocrc_s:.1%} of the zstd floor (wall), {floor_cpu / nocrc_cpu:.1%} (CPU)"
        )
        for label, ahead, what in (
            ("in line", False, "read_ahead=False: one thread"),
            ("read-ahead", True, "read_ahead=True: a worker thread decompresses, reads heads"),
        ):
            line_s, line_n, line_cpu, line_main = min(
                time_imufdi(base, read_ahead=ahead) for _ in range(3)
            )
            assert line_n == n_messages, (line_n, n_messages)
            print(
                f"reader, {label:<13}: {line_s:7.2f} s  {n_messages / line_s:12,.0f} msg/s,"
                f" {floor_s / line_s:.1%} of the zstd floor (wall), {floor_cpu / line_cpu:.1%}"
                f" (CPU {line_cpu:.2f} s), calling thread {line_main:.2f} s ({what})"
            )
        if args.malloc:
            for label, extra in (("fresh process", {}), ("+ glibc keeps memory", KEEP_MEMORY)):
                r_wall, r_cpu, f_wall, f_cpu = time_in_process(base, extra)
                print(
                    f"in line, {label:<20}: reader {r_wall:.2f} s (CPU {r_cpu:.2f} s), floor"
                    f" {f_wall:.2f} s (CPU {f_cpu:.2f} s): {f_wall / r_wall:.1%} wall,"
                    f" {f_cpu / r_cpu:.1%} CPU"
                )
        ref_s, ref_n = time_mcap_ros2(base, args.baseline_messages)
        ref_rate = ref_n / ref_s
        print(
            f"mcap-ros2-support    : {ref_s:7.2f} s  {ref_rate:12,.0f} msg/s"
            f" ({ref_n:,} messages decoded)"
        )
        print(
            f"speed-up             : {ours_rate / ref_rate:7.1f} x  (target >= 25 x, >= 1e6 msg/s)"
        )
        print(f"load average: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
        if not args.skip_memory:
            long = Path(tmp) / "long.mcap"
            make_log(long, args.imus, args.samples * 10)
            rss_base = peak_rss_reading(generated)
            rss_long = peak_rss_reading(long)
            print(
                f"peak RSS reading     : base {rss_base / 1024:.1f} MB, 10x longer"
                f" {rss_long / 1024:.1f} MB (+{100 * (rss_long / rss_base - 1):.1f} %, target <= 10 %)"
            )


if __name__ == "__main__":
    main()
