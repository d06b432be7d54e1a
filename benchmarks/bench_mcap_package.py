"""The MCAP code against the ``mcap`` package on the same files, same run: should the
package do the parts where speed does not matter? (docs/architecture.md)

Usage: python benchmarks/bench_mcap_package.py [--seconds 20] [--long-minutes 10]

Makes, at run time in a temporary directory, a ``--seconds`` log and a ``--long-minutes``
log (16 IMUs at 1 kHz), then measures the CPU time of this process for:

- iterating every raw message (no CDR decoding) of the short log: ``McapSource.batches``
  against the package's seeking and non-seeking readers (``iter_messages``);
- writing those messages again with zstd chunks: ``McapWriter.add_batch`` (CPU of all
  threads) against the package's ``Writer.add_message``;
- reading the summary and every metadata record of each log, what ``imufdi info`` needs:
  ``McapSource`` opening the file against ``make_reader(...).get_summary()`` and
  ``iter_metadata()`` (best of 5);
- importing the package (a fresh interpreter, against a bare one).

Prints each pair, the ratio and the load average (a shared 2-core machine: the ratios are
the claim).
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from mcap.reader import NonSeekingReader, make_reader
from mcap.writer import CompressionType, Writer

from imufdi_cli.mcapio import McapSource, McapWriter
from imufdi_cli.pipeline import simulate_file


def _cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def _timed(fn) -> tuple[float, object]:  # type: ignore[no-untyped-def]
    start = _cpu()
    value = fn()
    return _cpu() - start, value


def _line(what: str, ours: float, theirs: float, unit: str = "s") -> None:
    print(
        f"  {what:52s} imufdi {ours:9.4f} {unit}   mcap {theirs:9.4f} {unit}   {theirs / ours:6.1f}x"
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=20.0, help="short log length")
    parser.add_argument("--long-minutes", type=float, default=10.0, help="long log length")
    args = parser.parse_args()
    print("load average before: " + " ".join(f"{x:.2f}" for x in os.getloadavg()) + " (2 cores)")
    with tempfile.TemporaryDirectory(prefix="imufdi-bench-mcap-") as tmp:
        work = Path(tmp)
        short, long = work / "short.mcap", work / "long.mcap"
        options = {"imus": 16, "rate": "1kHz", "motion": "turntable"}
        simulate_file(None, str(short), seed=0, options={**options, "duration": f"{args.seconds}s"})
        simulate_file(
            None, str(long), seed=0, options={**options, "duration": f"{args.long_minutes}min"}
        )

        def ours_read() -> int:
            with McapSource(str(short)) as source:
                return sum(len(batch) for batch in source.batches())

        def seeking() -> int:
            with open(short, "rb") as f:
                return sum(1 for _ in make_reader(f).iter_messages(log_time_order=False))

        def non_seeking() -> int:
            with open(short, "rb") as f:
                return sum(1 for _ in NonSeekingReader(f).iter_messages())

        ours_s, n = _timed(ours_read)
        with McapSource(str(short)) as source:  # the messages the writers write (untimed)
            channels, batches = source.channels, list(source.batches())
        seek_s, n_seek = _timed(seeking)
        stream_s, n_stream = _timed(non_seeking)
        assert n == n_seek == n_stream, (n, n_seek, n_stream)
        print(f"{args.seconds:g} s log, 16 IMUs at 1 kHz: {n:,} messages")
        _line("raw messages, seeking reader", ours_s, seek_s)
        _line("raw messages, non-seeking reader", ours_s, stream_s)

        def ours_write() -> None:
            with McapWriter(str(work / "ours.mcap")) as writer:
                writer.copy_channels(channels)
                for batch in batches:
                    writer.add_batch(batch)

        def theirs_write() -> None:
            with open(work / "theirs.mcap", "wb") as f:
                writer = Writer(f, compression=CompressionType.ZSTD)
                writer.start()
                schema_ids: dict[str, int] = {}
                ids = {}
                for cid, channel in channels.items():
                    schema = channel.schema
                    if schema.name not in schema_ids:
                        schema_ids[schema.name] = writer.register_schema(
                            schema.name, schema.encoding, schema.data
                        )
                    ids[cid] = writer.register_channel(
                        topic=channel.topic,
                        message_encoding=channel.message_encoding,
                        schema_id=schema_ids[schema.name],
                        metadata=dict(channel.metadata),
                    )
                for batch in batches:
                    for i in range(len(batch)):
                        writer.add_message(
                            channel_id=ids[int(batch.channel_id[i])],
                            log_time=int(batch.log_time[i]),
                            publish_time=int(batch.publish_time[i]),
                            data=batch.payload(i),
                            sequence=int(batch.sequence[i]),
                        )
                writer.finish()

        ours_w, _ = _timed(ours_write)  # the writer's threads' CPU is the process's
        theirs_w, _ = _timed(theirs_write)
        _line("write the same messages, zstd chunks", ours_w, theirs_w)

        for label, path in (("short", short), (f"{args.long_minutes:g}-minute", long)):

            def ours_summary(path: Path = path) -> object:
                with McapSource(str(path)) as source:
                    return source.metadata

            def theirs_summary(path: Path = path) -> object:
                with open(path, "rb") as f:
                    reader = make_reader(f)
                    return reader.get_summary(), list(reader.iter_metadata())

            best_ours = min(_timed(ours_summary)[0] for _ in range(5))
            best_theirs = min(_timed(theirs_summary)[0] for _ in range(5))
            size = path.stat().st_size >> 20
            _line(
                f"summary + metadata, {label} log ({size} MiB), ms",
                best_ours * 1e3,
                best_theirs * 1e3,
                "ms",
            )

    def interpreter(code: str) -> float:
        runs = []
        for _ in range(7):
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            subprocess.run([sys.executable, "-c", code], check=True)
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            runs.append(after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime)
        return statistics.median(runs)

    bare, package = interpreter("pass"), interpreter("import mcap.reader, mcap.writer")
    print(
        f"  import mcap.reader, mcap.writer: +{(package - bare) * 1e3:.0f} ms of CPU over a bare interpreter"
    )
    print("load average after: " + " ".join(f"{x:.2f}" for x in os.getloadavg()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
