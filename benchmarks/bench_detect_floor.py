"""Benchmark: the floor of ``detect -d glt --no-explain``, as multiples of ``imufdi info``.

What any ``detect --no-explain`` must do whatever its detector, given that the output is
the input copied verbatim plus a per-sample ``FdiStatus`` stream per status channel, and
that reading stays pure Python and numpy: read the log (the IMU values decoded and
aligned into blocks), copy its chunks into the output, and build, compress and write
the status records. The **floor** is a process that does exactly that with the
package's own code paths (those of ``imufdi_cli/detect.py``: ``McapSource`` with the raw
chunks kept, ``ImuArrayReader.stream``, ``mcapio.passthrough.ChannelCopier``,
``McapWriter.add_raw_chunk``, ``mcapio.status.status_records`` and ``add_records``, the
same zstd compression and 1 MiB chunks) and no detection work at all: no detector, no
conditioner, no calibration window, no alarm or episode events, no ``imufdi.detect.*``
metadata record (the input's metadata records are copied, as detect copies them).

Its status rows have detect's layout for glt (one row per aligned sample on each of
``/imufdi/glt/gyro`` and ``/imufdi/glt/accel``, n = the sensors of that type: ``scores``
float64 x n, ``isolated_set`` n bytes, no per-sensor amplitudes; threshold constant,
alarm false, isolated -1, amplitude NaN). Statistic and scores are squares of standard
normal draws from ``numpy.random.default_rng(1)``, drawn per block: chi-square-like
float64 values whose mantissas zstd cannot squeeze (nor can it glt's), so the floor
compresses and writes about the bytes detect does (the sizes of both outputs, and their
status row counts per topic, are printed to show it).

What the floor does that detect does not: it draws its values (about 6 M normal draws
for 10 minutes of 16 IMUs, a cost that stands for the detector's output); that draw is
timed again in the benchmark's own process and printed, with the floor less it. What
detect does that the floor does not, beyond detection: the alarm events (about 20,000
small messages on the faulty 10-minute log) and its metadata record, and the command
line (click and the commands' modules; the floor is a plain script, so a fourth child,
``floor + CLI import``, imports ``imufdi_cli.cli`` first to show what that adds).

Timed, in interleaved rounds, each a fresh ``python`` child with the previous output
removed before it starts (outside its time), the CPU (user + system of the child, from
``os.wait4``) and wall time, minimum over ``--repeat`` rounds, and ratios against the
``info`` of the same run:

1. ``python -m imufdi_cli info LOG``
2. ``python -m imufdi_cli detect -d glt --no-explain LOG -o OUT``
3. ``python benchmarks/bench_detect_floor.py --floor-child LOG OUT`` (the floor)
4. the same with ``--with-cli``

then floor/info, detect/info and (detect - floor)/info, what the detection itself costs.
``--parts`` also times the floor without the status rows and without the copy (``--skip``
of the child), and prints what the verbatim copy and the status rows each add to reading.
The log is made at run time as ``bench_targets.py`` makes it (paper-table4, 16 IMUs,
``--minutes`` long, simulation and injection seed 1, a tuning seed) unless ``--log`` is
given. Children read compiled bytecode from a cache made once (``bench_targets.py``).

    python benchmarks/bench_detect_floor.py                  # 10-minute log, 3 rounds
    python benchmarks/bench_detect_floor.py --repeat 5 --log faulty.mcap --parts
"""

from __future__ import annotations

import argparse
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from imufdi_cli.errors import ImufdiError
from imufdi_cli.mcapio import ImuArrayReader, McapSource, McapWriter
from imufdi_cli.mcapio.passthrough import ChannelCopier
from imufdi_cli.mcapio.status import register_status_channel, status_records, status_topic

HERE = Path(__file__).resolve().parent

#: a constant threshold for the floor's rows (glt's is a chi-square quantile, as constant)
FLOOR_THRESHOLD = 15.0
#: glt tests a sensor type with at least this many sensors (a parity test needs 4)
MIN_SENSORS = 4
DETECTOR = "glt"


@dataclass
class FloorRows:
    """Status rows of N samples in a real glt row's layout (``mcapio.status.DetectionRows``):
    no alarm, no isolation, the statistic and scores given (float64, (N,) and (N, n))."""

    statistic: np.ndarray
    scores: np.ndarray
    threshold: np.ndarray = field(init=False)
    alarm: np.ndarray = field(init=False)
    isolated: np.ndarray = field(init=False)
    amplitude: np.ndarray = field(init=False)
    amplitudes: np.ndarray | None = None

    def __post_init__(self) -> None:
        n = self.statistic.shape[0]
        self.threshold = np.full(n, FLOOR_THRESHOLD)
        self.alarm = np.zeros(n, dtype=bool)
        self.isolated = np.full(n, -1, dtype=np.int32)
        self.amplitude = np.full(n, np.nan)

    def __len__(self) -> int:
        return int(self.statistic.shape[0])

    def isolation_set(self) -> np.ndarray:
        return np.zeros(self.scores.shape, dtype=bool)

    def amplitude_set(self) -> np.ndarray:
        return np.full(self.scores.shape, np.nan)


def floor_rows(rng: np.random.Generator, n_rows: int, n_sensors: int) -> FloorRows:
    """Rows of ``n_rows`` samples: statistic and ``n_sensors`` scores, squared standard
    normal draws (one (N, n + 1) draw, squared in place)."""
    draws = rng.standard_normal((n_rows, n_sensors + 1))
    np.square(draws, out=draws)
    return FloorRows(statistic=draws[:, 0], scores=draws[:, 1:])


def floor_detect(
    log: str | os.PathLike[str],
    out: str | os.PathLike[str],
    *,
    copy: bool = True,
    status: bool = True,
) -> dict[str, int]:
    """Read ``log`` as detect does, copy it into ``out`` verbatim and write a status
    channel of random rows per glt sensor type; returns the rows written per topic.

    ``copy=False`` leaves out the copy (input channels, messages and metadata records),
    ``status=False`` the status channels: the parts of the floor (``--parts``).

    Raises
    ------
    imufdi_cli.errors.ImufdiError
        What the package's reader or writer raise on a bad log or output path.
    """
    source = McapSource(str(log), keep_raw_chunks=True)
    rows_written: dict[str, int] = {}
    try:
        reader = ImuArrayReader(source)
        array = reader.array
        types = [t for t in array.sensor_types() if array.n_sensors(t) >= MIN_SENSORS]
        rng = np.random.default_rng(1)
        with McapWriter(str(out), compression="zstd") as writer:
            copier = ChannelCopier(writer)
            if copy:
                copier.ensure(source.channels, set(source.channels))
            if not status:
                types = []
            channels = {
                t: register_status_channel(writer, DETECTOR, t, array.sensor_ids(t)) for t in types
            }
            sizes = {t: array.n_sensors(t) for t in types}
            rows_written = {status_topic(DETECTOR, t): 0 for t in types}
            for batch, block in reader.stream():
                if copy and len(batch):
                    seen = np.flatnonzero(np.bincount(batch.channel_id.astype(np.intp)))
                    new = set(seen.tolist()) - copier.known
                    if new:
                        copier.ensure(source.channels, new)
                    _copy(source, writer, copier, batch)
                n = len(block)
                if not n:
                    continue
                t_ns = np.asarray(block.t_ns, dtype=np.int64)
                for t in types:
                    rows = floor_rows(rng, n, sizes[t])
                    channel = channels[t]
                    writer.add_records(
                        status_records(channel, t_ns, rows, t_ns), np.full(n, channel), t_ns
                    )
                    rows_written[status_topic(DETECTOR, t)] += n
            for name, data in source.metadata.items() if copy else ():
                writer.add_metadata(name, data)
    finally:
        source.close()
    return rows_written


def _copy(source: McapSource, writer: McapWriter, copier: ChannelCopier, batch: Any) -> None:
    """A raw input batch into the output, as detect copies it: whole input chunks of the
    same compression verbatim, the rest as records."""
    runs = source.raw_chunks(batch) if copier.identity else None
    if runs is None:
        writer.add_batch(copier.remap(batch))
        return
    start = 0
    for raw, count, records_at in runs:
        part = batch.select(slice(start, start + count))
        if raw is not None and raw.compression == writer.compression:
            writer.add_raw_chunk(raw, part, records_at)
        else:
            writer.add_batch(part)
        start += count


def _floor_child(log: str, out: str, with_cli: bool, skip: list[str]) -> int:
    if with_cli:  # what the command line adds to a start: click and the commands' modules
        import imufdi_cli.cli  # noqa: F401

    try:
        floor_detect(log, out, copy="copy" not in skip, status="status" not in skip)
    except ImufdiError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return exc.exit_code
    return 0


def _make_log(runner: Any, workdir: Path, minutes: float) -> Path:
    """The faulty paper-table4 log of ``bench_targets.py`` (seed 1)."""
    from bench_targets import make_log

    return make_log(runner, workdir, minutes)


def _status_counts(path: Path) -> dict[str, int]:
    """Messages per ``/imufdi/`` topic of an output (from its summary section)."""
    with McapSource(str(path)) as source:
        counts = source.summary_channel_counts or {}
        return {
            c.topic: int(counts.get(c.id, 0))
            for c in source.channels.values()
            if c.topic.startswith("/imufdi/")
        }


def _draw_seconds(log: Path, repeat: int) -> float:
    """CPU seconds (this process, min of ``repeat``) of the floor's value draws alone, for
    the blocks the reader makes of ``log``: the random numbers stand for a detector's
    output, so their cost is work a detect without detection would not do (printed, to
    subtract)."""
    import time

    with ImuArrayReader(str(log)) as reader:
        array = reader.array
        sizes = [array.n_sensors(t) for t in array.sensor_types()]
        sizes = [n for n in sizes if n >= MIN_SENSORS]
        blocks = [len(block) for _, block in reader.stream() if len(block)]
    best = float("inf")
    for _ in range(repeat):
        rng = np.random.default_rng(1)
        start = time.process_time()
        for rows in blocks:
            for sensors in sizes:
                floor_rows(rng, rows, sensors)
        best = min(best, time.process_time() - start)
    return best


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--floor-child",
        nargs=2,
        metavar=("LOG", "OUT"),
        help="run the floor once on LOG, writing OUT (what the benchmark times)",
    )
    parser.add_argument(
        "--with-cli", action="store_true", help="with --floor-child: import imufdi_cli.cli first"
    )
    parser.add_argument(
        "--skip",
        action="append",
        choices=("copy", "status"),
        default=[],
        help="with --floor-child: leave out the copy of the input or the status rows",
    )
    parser.add_argument(
        "--parts",
        action="store_true",
        help="also time the floor's parts: reading alone, with the copy, with the status rows",
    )
    parser.add_argument("--log", type=Path, help="the log to time (default: made at run time)")
    parser.add_argument("--minutes", type=float, default=10.0, help="length of the made log")
    parser.add_argument("--repeat", type=int, default=3, help="interleaved rounds (min kept)")
    parser.add_argument(
        "--dir", type=Path, help="where to put the log and outputs, kept (default: a temporary one)"
    )
    args = parser.parse_args(argv)
    if args.floor_child:
        log, out = args.floor_child
        return _floor_child(log, out, with_cli=args.with_cli, skip=args.skip)
    if args.repeat < 1:
        parser.error(f"--repeat must be >= 1, got {args.repeat}")
    return _benchmark(args)


def _benchmark(args: argparse.Namespace) -> int:
    import shutil
    import tempfile

    if args.dir is not None:
        args.dir.mkdir(parents=True, exist_ok=True)
        return _measure(args, args.dir.resolve())
    workdir = Path(tempfile.mkdtemp(prefix="imufdi-bench-floor-"))
    try:
        return _measure(args, workdir)
    finally:  # the log and outputs (some 300 MB for 10 minutes) are not left behind
        shutil.rmtree(workdir, ignore_errors=True)


def _measure(args: argparse.Namespace, workdir: Path) -> int:
    import statistics

    sys.path.insert(0, str(HERE))
    from bench_targets import TREE, Runner, load

    runner = Runner(TREE, workdir / "pycache")
    print(f"load average before: {load()} ({os.cpu_count()} cores)")
    if args.log is not None:
        log = args.log.resolve()
        if not log.is_file():
            print(f"error: --log {log}: no such file", file=sys.stderr)
            return 2
        made = "given"
    else:
        log = _make_log(runner, workdir, args.minutes)
        made = f"paper-table4, 16 IMUs, 100 Hz, {args.minutes:g} min, faults injected, seed 1"
    print(f"log: {log} ({log.stat().st_size / 1e6:.1f} MB; {made})")
    detect_out, floor_out = workdir / "detect.mcap", workdir / "floor.mcap"
    cli_out = workdir / "floor-cli.mcap"
    script = str(HERE / "bench_detect_floor.py")
    commands: list[tuple[str, list[str], Path | None]] = [
        ("info", ["-m", "imufdi_cli", "info", str(log)], None),
        (
            "detect --no-explain",
            [
                *("-m", "imufdi_cli", "detect", "-d", "glt", "--no-explain"),
                *(str(log), "-o", str(detect_out)),
            ],
            detect_out,
        ),
        ("floor", [script, "--floor-child", str(log), str(floor_out)], floor_out),
        (
            "floor + CLI import",
            [script, "--floor-child", str(log), str(cli_out), "--with-cli"],
            cli_out,
        ),
    ]
    #: the floor's parts: (name, --skip arguments)
    parts = [
        ("floor: read only", ["--skip", "copy", "--skip", "status"]),
        ("floor: read + copy", ["--skip", "status"]),
        ("floor: read + status", ["--skip", "copy"]),
    ]
    for name, skip in parts if args.parts else ():
        part = workdir / f"part-{len(commands)}.mcap"
        commands.append((name, [script, "--floor-child", str(log), str(part), *skip], part))
    # one untimed run of each first: the bytecode cache is filled outside the timings
    for _, argv, out in commands:
        if out is not None:
            out.unlink(missing_ok=True)
        runner.run_python(argv)
    cpu: dict[str, list[float]] = {name: [] for name, _, _ in commands}
    wall: dict[str, list[float]] = {name: [] for name, _, _ in commands}
    for round_index in range(args.repeat):
        for name, argv, out in commands:
            if out is not None:
                # a fresh output, as at a first run (the release of the previous file's
                # blocks is system CPU, and is kept out of the timing)
                out.unlink(missing_ok=True)
            seconds, elapsed, _ = runner.run_python(argv)
            cpu[name].append(seconds)
            wall[name].append(elapsed)
        print(f"round {round_index + 1}/{args.repeat} done, load average {load()}")
    info = min(cpu["info"])
    print(f"\nCPU s (user + sys, min of {args.repeat}), ratio to info of the same run:")
    for name, _, _ in commands:
        best = min(cpu[name])
        paired = statistics.median(c / i for c, i in zip(cpu[name], cpu["info"], strict=True))
        print(
            f"  {name:22s}  CPU {best:6.3f} s  wall {min(wall[name]):6.3f} s"
            f"  = {best / info:5.2f}x info (median of rounds {paired:5.2f}x)"
        )
    floor, detect = min(cpu["floor"]), min(cpu["detect --no-explain"])
    target = 1.3
    print(
        f"\n  floor / info             {floor / info:5.2f}x"
        f"  ({'above' if floor / info > target else 'not above'} the {target:g}x target)"
    )
    print(f"  detect / info            {detect / info:5.2f}x")
    print(f"  (detect - floor) / info  {(detect - floor) / info:5.2f}x  (the detection itself)")
    if args.parts:
        read = min(cpu["floor: read only"])
        copying = min(cpu["floor: read + copy"]) - read
        rows = min(cpu["floor: read + status"]) - read
        print(f"  of the floor, the verbatim copy   {copying / info:5.2f}x info")
        print(f"  of the floor, the status rows     {rows / info:5.2f}x info")
    counts = {"detect": _status_counts(detect_out), "floor": _status_counts(floor_out)}
    draws = _draw_seconds(log, args.repeat)
    print(
        f"  of the floor, drawing its values {draws:.3f} s = {draws / info:.2f}x info"
        f" (in this process, min of {args.repeat}): floor without them"
        f" {(floor - draws) / info:5.2f}x info"
    )
    sizes = {"detect": detect_out.stat().st_size, "floor": floor_out.stat().st_size}
    ratio = sizes["floor"] / sizes["detect"]
    print(
        f"\noutputs: detect {sizes['detect'] / 1e6:.1f} MB, floor {sizes['floor'] / 1e6:.1f} MB"
        f" (floor / detect {ratio:.3f}; input {log.stat().st_size / 1e6:.1f} MB)"
    )
    for topic in sorted(set(counts["detect"]) | set(counts["floor"])):
        print(
            f"  {topic:24s} detect {counts['detect'].get(topic, 0):9,d} messages"
            f"  floor {counts['floor'].get(topic, 0):9,d}"
        )
    if abs(ratio - 1.0) > 0.10:
        print(
            "  the floor's output differs from detect's by more than 10 %: its status rows"
            " do not stand for detect's (see the counts above)"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
