#!/usr/bin/env python3
"""Mutation fuzz of imufdi's inputs through the CLI (docs/testing.md, "Fuzzing").

Builds a few small logs (chunked zstd, chunked lz4 with small chunks, un-chunked, a
detector output, a static log for calibrate) and makes mutated inputs of five families,
in turn:

- ``bytes``: bit flips, random bytes, cuts, huge or zero u64 fields, deleted, duplicated
  or zeroed ranges, a zero-filled tail (1-3 mutations stacked);
- ``metadata``: an ``imufdi.*`` metadata record (faults, detect, array, ingest) replaced by
  hostile JSON: null, lists, numbers, strings, nesting 100,000 deep, wrong types, NaN,
  integers beyond 64 bits, times beyond any log;
- ``numeric``: IMU values NaN, inf, 1e308, subnormal or -0; stamps duplicated, backwards,
  far in the future or 0; a message log time beyond 2^63 ns;
- ``gaps``: an IMU topic that stops, slows to a fraction of the rate or starts late; a
  three-hour gap in the whole log; messages out of order;
- ``aliases``: the command's outputs pointed at its input (by path, symlink, hard link,
  the file stdin reads, stdout opened on it with ``1<>`` or ``>>``, an output derived
  from another, two outputs on one file, an empty name).

Every mutated file goes through ``info``, ``detect``, ``inject``, ``report`` and
``calibrate`` (one of them reading it through a pipe on stdin; an alias case through the
command its alias applies to). It counts, per command and in total:

- exit codes (4 = internal error),
- tracebacks on stderr, empty error/warning messages (nothing after the colon), error
  messages over more than one line,
- hangs (killed at ``--timeout``),
- peak RSS of each run (from ``wait4``; runs are forked from a parent that has imported
  imufdi, numpy and scipy, as a fresh process would),
- inputs modified by the run (any alias case included), output files left after a
  failed run, and leftover temporary files in the output directory,
- alias cases that were not refused (exit 2).

Usage::

    PYTHONPATH=. python tools/fuzz_inputs.py --files 1000 --seed 1 --jobs 2
    PYTHONPATH=. python tools/fuzz_inputs.py --files 50 --families metadata,gaps

The mutations depend only on ``--seed``. Prints a table of the counts (``--json`` for
JSON) and the first few examples of every bad category.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import hashlib
import io
import json
import os
import resource
import shutil
import signal
import struct
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

COMMANDS = ("info", "detect", "inject", "report", "calibrate")
FAMILIES = ("bytes", "metadata", "numeric", "gaps", "aliases")
FAULT = "step:imu0.gyro.x,at=0.5s,amp=0.9deg/s"


# --- base files ---------------------------------------------------------------------------


def _cli(argv: list[str]) -> None:
    from imufdi_cli.cli import main

    try:
        main(argv)
    except SystemExit as exc:
        if exc.code not in (0, None):
            raise RuntimeError(f"imufdi {' '.join(argv)} failed with {exc.code}") from None


def build_bases(workdir: Path) -> dict[str, Path]:
    """Small valid logs of every kind the reader meets."""
    from mcap.writer import Writer

    from imufdi_cli.mcapio import McapSource, McapWriter

    sim = workdir / "sim-zstd.mcap"
    _cli(["simulate", "--imus", "6", "--duration", "3s", "--seed", "3", "-o", str(sim)])
    lz4 = workdir / "sim-lz4-small-chunks.mcap"
    with McapSource(sim) as source, McapWriter(lz4, compression="lz4", chunk_size=8192) as out:
        out.copy_channels(source.channels)
        for name, values in source.metadata.items():
            out.add_metadata(name, values)
        for batch in source.batches():
            out.add_batch(batch)
    unchunked = workdir / "sim-unchunked.mcap"
    with McapSource(sim) as source, open(unchunked, "wb") as stream:
        writer = Writer(stream, use_chunking=False)
        writer.start(profile="ros2", library="fuzz")
        for name, values in source.metadata.items():
            writer.add_metadata(name, values)
        ids: dict[int, int] = {}
        schemas: dict[int, int] = {}
        for batch in source.batches():
            for i in range(len(batch)):
                cid = int(batch.channel_id[i])
                if cid not in ids:
                    channel = source.channels[cid]
                    schema = channel.schema
                    assert schema is not None
                    if schema.id not in schemas:
                        schemas[schema.id] = writer.register_schema(
                            schema.name, schema.encoding, schema.data
                        )
                    ids[cid] = writer.register_channel(
                        channel.topic, channel.message_encoding, schemas[schema.id]
                    )
                t = int(batch.log_time[i])
                writer.add_message(ids[cid], t, batch.payload(i), t, int(batch.sequence[i]))
        writer.finish()
    injected = workdir / "injected.mcap"
    _cli(["inject", str(sim), "--fault", FAULT, "-o", str(injected)])
    detected = workdir / "detected.mcap"
    _cli(["detect", str(injected), "-d", "glt", "-o", str(detected)])
    static = workdir / "static.mcap"  # at rest: calibrate runs every pass on it
    options = ["--imus", "6", "--duration", "4s", "--motion", "static", "--seed", "4"]
    _cli(["simulate", *options, "-o", str(static)])
    array = workdir / "array.toml"  # an input file of detect --array and calibrate --array
    from imufdi_cli.mcapio import ImuArrayReader

    with ImuArrayReader(sim) as reader:
        array.write_text(reader.array.to_toml())
    return {
        "zstd": sim,
        "lz4": lz4,
        "unchunked": unchunked,
        "detected": detected,
        "static": static,
        "array": array,
    }


#: bases mutated by each family (the array file is an input of the alias cases only)
FAMILY_BASES = {
    "bytes": ("zstd", "lz4", "unchunked", "detected", "static"),
    "metadata": ("detected", "static"),
    "numeric": ("zstd", "static", "detected"),
    "gaps": ("zstd", "static", "detected"),
    "aliases": ("zstd", "detected", "static"),
}


# --- mutations ----------------------------------------------------------------------------

_U64 = [0, 1, 2**31, 2**32 - 1, 2**40, 2**63, 2**64 - 1, 77_309_414_278]


def mutate(data: bytes, rng: np.random.Generator) -> tuple[bytes, str]:
    """1-3 stacked mutations; returns the bytes and a short description."""
    out = bytearray(data)
    done = []
    if rng.random() < 0.05:  # a file not completely written: a zero-filled tail
        cut = int(rng.integers(8, len(out)))
        zeros = int(rng.choice([1 << 10, 1 << 20, 8 << 20]))
        return bytes(out[:cut]) + bytes(zeros), f"zero-tail@{cut}+{zeros}"
    for _ in range(int(rng.integers(1, 4))):
        if len(out) <= 9:
            break
        kind = int(rng.integers(0, 7))
        at = int(rng.integers(8, len(out)))
        if kind == 0:
            bit = int(rng.integers(0, 8))
            out[at] ^= 1 << bit
            done.append(f"flip@{at}.{bit}")
        elif kind == 1:
            n = int(rng.integers(1, 32))
            out[at : at + n] = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
            done.append(f"random@{at}+{n}")
        elif kind == 2:
            del out[at:]
            done.append(f"cut@{at}")
        elif kind == 3:
            value = _U64[int(rng.integers(0, len(_U64)))]
            out[at : at + 8] = struct.pack("<Q", value)
            done.append(f"u64@{at}={value}")
        elif kind == 4:
            n = int(rng.integers(1, 512))
            del out[at : at + n]
            done.append(f"delete@{at}+{n}")
        elif kind == 5:
            n = int(rng.integers(1, 512))
            out[at:at] = out[at : at + n]
            done.append(f"duplicate@{at}+{n}")
        else:
            n = int(rng.integers(1, 256))
            out[at : at + n] = bytes(len(out[at : at + n]))
            done.append(f"zero@{at}+{n}")
    return bytes(out), ",".join(done)


def _copy(
    source: Path,
    target: Path,
    *,
    metadata: dict[str, dict[str, str]] | None = None,
    keep=None,
    log_time=None,
) -> None:
    """``source`` rewritten with the mcap package (so that imufdi's writer checks nothing):
    its metadata replaced by ``metadata`` (when given), only the messages ``keep(channel,
    message, index)`` accepts, log times from ``log_time(channel, message, index)``."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    with open(source, "rb") as stream, open(target, "wb") as out:
        reader = make_reader(stream)
        writer = Writer(out)
        writer.start("ros2", "fuzz")
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for index, (schema, channel, message) in enumerate(reader.iter_messages()):
            if keep is not None and not keep(channel, message, index):
                continue
            if schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(
                    schema.name, schema.encoding, schema.data
                )
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schemas[schema.id], channel.metadata
                )
            t = message.log_time if log_time is None else log_time(channel, message, index)
            writer.add_message(channels[channel.id], t, message.data, message.publish_time)
        records = (
            {r.name: dict(r.metadata) for r in reader.iter_metadata()}
            if metadata is None
            else metadata
        )
        for name, values in records.items():
            writer.add_metadata(name, values)
        writer.finish()


def _hostile_values(rng: np.random.Generator) -> object:
    """A JSON value no imufdi record holds where it is put."""
    choices = [
        None,
        [],
        {},
        5,
        -1,
        "x",
        True,
        2**70,
        -(2**70),
        1e308,
        float("nan"),
        float("inf"),
        [None] * 3,
        ["x", 1],
        {"x": [1, {"y": None}]},
    ]
    return choices[int(rng.integers(0, len(choices)))]


def _replace_somewhere(value: object, rng: np.random.Generator, depth: int = 0) -> object:
    """``value`` (decoded JSON) with one element, at any depth, replaced by a hostile one."""
    if isinstance(value, dict) and value and rng.random() < 0.8:
        key = sorted(value)[int(rng.integers(0, len(value)))]
        return {**value, key: _replace_somewhere(value[key], rng, depth + 1)}
    if isinstance(value, list) and value and rng.random() < 0.8:
        i = int(rng.integers(0, len(value)))
        return [*value[:i], _replace_somewhere(value[i], rng, depth + 1), *value[i + 1 :]]
    return _hostile_values(rng)


def mutate_metadata(source: Path, target: Path, rng: np.random.Generator) -> str:
    """One ``imufdi.*`` metadata record of ``source`` replaced by hostile JSON."""
    from mcap.reader import make_reader

    with open(source, "rb") as stream:
        records = {r.name: dict(r.metadata) for r in make_reader(stream).iter_metadata()}
    names = [*sorted(n for n in records if n.startswith("imufdi.")), "imufdi.ingest"]
    name = names[int(rng.integers(0, len(names)))]
    kind = int(rng.integers(0, 6))
    original = records.get(name, {}).get("json", "{}")
    if kind == 0:
        text = ["null", "[]", "5", '"x"', "true", "{", "", '"\\ud800"', "NaN"][
            int(rng.integers(0, 9))
        ]
    elif kind == 1:  # nested far beyond any decoder's recursion limit
        depth = int(rng.choice([100, 1000, 100_000]))
        text = (
            "[" * depth + "]" * depth if rng.random() < 0.5 else '{"a":' * depth + "1" + "}" * depth
        )
    elif kind == 2:
        records[name] = {"other": original}  # no "json" entry
        text = None
    else:  # a field of the real record replaced
        try:
            decoded = json.loads(original)
        except ValueError:
            decoded = {}
        text = json.dumps(_replace_somewhere(decoded, rng))
    if text is not None:
        records[name] = {"json": text}
    _copy(source, target, metadata=records)
    return f"{name}:{['scalar', 'deep', 'no-json', 'field', 'field', 'field'][kind]}"


_HOSTILE_NUMBERS = [np.nan, np.inf, -np.inf, 1e308, -1e308, 5e-324, -0.0, 1e30]


def mutate_numeric(source: Path, target: Path, rng: np.random.Generator) -> str:
    """IMU values or stamps no sensor gives, or a message log time beyond 2^63 ns."""
    from imufdi_cli.log import ImuBlock
    from imufdi_cli.mcapio import McapSource, read_array, write_array

    kind = int(rng.integers(0, 4))
    if kind == 3:  # one message's log time beyond int64
        which = int(rng.integers(0, 50))
        shift = int(rng.choice([1, 2**40, 2**63 - 1]))
        _copy(
            source,
            target,
            log_time=lambda c, m, i: (1 << 63) + shift if i == which else m.log_time,
        )
        return f"log-time>2^63@{which}"
    with McapSource(source) as src:
        metadata = {k: v for k, v in src.metadata.items() if k != "imufdi.array"}
    array, block = read_array(source)
    n = len(block)
    t = block.t_ns.copy()
    gyro = None if block.gyro is None else block.gyro.copy()
    accel = None if block.accel is None else block.accel.copy()
    what = ""
    if kind == 0:  # values
        value = _HOSTILE_NUMBERS[int(rng.integers(0, len(_HOSTILE_NUMBERS)))]
        data = gyro if (rng.random() < 0.5 or accel is None) else accel
        assert data is not None
        count = int(rng.integers(1, max(2, data.size // 10)))
        flat = data.reshape(-1)
        flat[rng.integers(0, flat.size, count)] = value
        what = f"values={value!r}x{count}"
    elif kind == 1:  # stamps
        a = int(rng.integers(0, n - 1))
        b = int(rng.integers(a + 1, n))
        how = int(rng.integers(0, 3))
        if how == 0:
            t[a:b] = t[a]  # duplicated
        elif how == 1:
            t[a:b] = t[a:b][::-1].copy()  # backwards
        else:
            t[a:] += int(rng.choice([10**15, 10**18]))  # far ahead
        what = f"stamps:{['duplicate', 'backwards', 'ahead'][how]}@{a}-{b}"
    else:  # a whole IMU constant or huge
        k = int(rng.integers(0, block.n_imus))
        value = float(rng.choice([0.0, 1e6, -1e6]))
        for data in (gyro, accel):
            if data is not None:
                data[:, k] = value
        what = f"imu{k}={value:g}"
    try:
        write_array(target, array, ImuBlock(t_ns=t, gyro=gyro, accel=accel), metadata=metadata)
    except Exception as err:  # the writer refuses some stamps (beyond int32 seconds)
        # the same stamps as log times, through the mcap package (which checks nothing)
        per_slot = {int(old): int(new) for old, new in zip(block.t_ns, t)}
        _copy(source, target, log_time=lambda c, m, i: per_slot.get(m.log_time, m.log_time))
        return f"{what}:as-log-times({type(err).__name__})"
    return what


def mutate_gaps(source: Path, target: Path, rng: np.random.Generator) -> str:
    """An IMU topic that stops, slows or starts late; a gap in the whole log; messages
    out of order."""
    from mcap.reader import make_reader

    with open(source, "rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        topics = sorted(c.topic for c in summary.channels.values() if c.topic.endswith("/data_raw"))
        start = summary.statistics.message_start_time
        end = summary.statistics.message_end_time
    topic = topics[int(rng.integers(0, len(topics)))]
    at = start + int(rng.random() * (end - start))
    kind = int(rng.integers(0, 5))
    if kind == 0:
        _copy(source, target, keep=lambda c, m, i: c.topic != topic or m.log_time < at)
        return f"{topic}:stops"
    if kind == 1:
        every = int(rng.choice([2, 3, 10]))
        _copy(
            source,
            target,
            keep=lambda c, m, i: c.topic != topic or m.sequence % every == 0 or i % every == 0,
        )
        return f"{topic}:1/{every}-rate"
    if kind == 2:
        _copy(source, target, keep=lambda c, m, i: c.topic != topic or m.log_time >= at)
        return f"{topic}:starts-late"
    if kind == 3:  # log times (not stamps) jump by three hours
        _copy(
            source,
            target,
            log_time=lambda c, m, i: m.log_time + (3 * 3600 * 10**9 if m.log_time >= at else 0),
        )
        return "log-time-gap-3h"
    order = list(range(0, 40))
    rng.shuffle(order)
    first = int(rng.integers(0, 200))
    _copy(
        source,
        target,
        log_time=lambda c, m, i: (
            m.log_time if not first <= i < first + 40 else m.log_time - order[i - first] * 1_000_000
        ),
    )
    return "out-of-order"


ALIAS_CASES = (
    "inject -o IN",
    "detect -o symlink",
    "detect -o hardlink",
    "report --json IN",
    "report --roc derived",
    "inject stdin -o IN",
    "ingest stdin -o IN",
    "inject -o - 1<> IN",
    "info --json >> IN",
    "report --markdown - >> IN",
    "report two outputs",
    "detect -o ''",
    "detect --array -o array",
    "calibrate --array -o array",
)


def alias_case(base: Path, array_file: Path, out_dir: Path, case: str) -> dict:
    """The command of one of :data:`ALIAS_CASES`, whose outputs alias its input: the argv,
    the input the run must leave as it was, stdin/stdout redirections (the run must exit
    2, refused before anything is written)."""
    log = out_dir / "in.mcap"
    shutil.copyfile(base, log)
    spec: dict = {"input": log, "stdin_path": None, "stdout": None, "made": []}
    if case == "inject -o IN":
        argv = ["inject", str(log), "--fault", FAULT, "-o", str(log)]
    elif case in ("detect -o symlink", "detect -o hardlink"):
        link = out_dir / "link.mcap"
        if case.endswith("symlink"):
            link.symlink_to(log)
        else:
            os.link(log, link)
        spec["made"] = [link.name]
        argv = ["detect", str(log), "-d", "glt", "-o", str(link)]
    elif case == "report --json IN":
        argv = ["report", str(log), "--json", str(log)]
    elif case == "report --roc derived":  # --roc r.csv with --plot also writes r.png: the input
        png = out_dir / "r.png"
        log.rename(png)
        spec["input"] = png
        argv = [
            "report",
            str(png),
            "--roc",
            str(out_dir / "r.csv"),
            "--plot",
            str(out_dir / "p.png"),
        ]
    elif case == "inject stdin -o IN":
        spec["stdin_path"] = log
        argv = ["inject", "-", "--fault", FAULT, "-o", str(log)]
    elif case == "ingest stdin -o IN":
        spec["stdin_path"] = log
        argv = ["ingest", "-", "-o", str(log)]
    elif case == "inject -o - 1<> IN":
        spec["stdout"] = (log, os.O_RDWR)
        argv = ["inject", str(log), "--fault", FAULT, "-o", "-"]
    elif case == "info --json >> IN":
        spec["stdout"] = (log, os.O_WRONLY | os.O_APPEND)
        argv = ["info", str(log), "--json"]
    elif case == "report --markdown - >> IN":
        spec["stdout"] = (log, os.O_WRONLY | os.O_APPEND)
        argv = ["report", str(log), "--markdown", "-"]
    elif case == "report two outputs":
        same = str(out_dir / "o.txt")
        argv = ["report", str(log), "--json", same, "--markdown", same]
    elif case == "detect -o ''":
        argv = ["detect", str(log), "-d", "glt", "-o", ""]
    else:
        array = out_dir / "array.toml"
        shutil.copyfile(array_file, array)
        spec["input"] = array
        spec["also"] = log  # the log must not change either
        if case.startswith("detect"):
            argv = ["detect", str(log), "-d", "glt", "--array", str(array), "-o", str(array)]
        else:
            argv = ["calibrate", str(log), "--array", str(array), "-o", str(array)]
    spec.update(argv=argv, case=case, command=argv[0])
    return spec


# --- running one command in a forked child ----------------------------------------------


@dataclass
class Outcome:
    command: str
    file: str
    mutation: str
    stdin: bool
    exit_code: int | None  # None: hang (killed)
    stderr: str
    peak_rss_kb: int
    input_modified: bool
    leftovers: list[str] = field(default_factory=list)
    outputs_after_failure: list[str] = field(default_factory=list)
    expect_exit: int | None = None  # an alias case: the run must be refused (2)


def _argv(command: str, source: str, out_dir: Path) -> tuple[list[str], list[str]]:
    """CLI arguments and the output files a successful run leaves."""
    if command == "info":
        return ["info", source], []
    if command == "detect":
        return ["detect", source, "-d", "glt", "-o", str(out_dir / "det.mcap")], ["det.mcap"]
    if command == "inject":
        return ["inject", source, "--fault", FAULT, "-o", str(out_dir / "inj.mcap")], ["inj.mcap"]
    if command == "calibrate":
        out = str(out_dir / "cal.toml")
        return ["calibrate", source, "--min-static", "1s", "-o", out], ["cal.toml"]
    return ["report", source, "--json", str(out_dir / "r.json")], ["r.json"]


def _child(
    argv: list[str],
    stdin_data: bytes | None,
    out_dir: Path,
    stdin_path: Path | None = None,
    stdout_file: tuple[Path, int] | None = None,
) -> None:
    """In the forked child: redirect stdio (stdin from ``stdin_data`` through a pipe or
    from the file ``stdin_path``; stdout to ``stdout_file`` opened with those flags, as
    ``1<> FILE`` or ``>> FILE``), run the CLI, exit with its code."""
    try:
        os.chdir(out_dir)
        if stdout_file is not None:
            stdout = os.open(stdout_file[0], stdout_file[1])
        else:
            stdout = os.open(out_dir / "stdout", os.O_WRONLY | os.O_CREAT, 0o644)
        stderr = os.open(out_dir / "stderr", os.O_WRONLY | os.O_CREAT, 0o644)
        os.dup2(stdout, 1)
        os.dup2(stderr, 2)
        # the standard streams on the new descriptors, whatever the parent had (a test
        # runner's capture): the CLI checks the files fds 0 and 1 are open on
        sys.stdout = open(1, "w", closefd=False)
        sys.stderr = open(2, "w", closefd=False)
        if stdin_path is not None:
            os.dup2(os.open(stdin_path, os.O_RDONLY), 0)
        elif stdin_data is not None:
            read_end, write_end = os.pipe()

            def feed() -> None:
                with open(write_end, "wb") as pipe:
                    try:
                        pipe.write(stdin_data)
                    except BrokenPipeError:
                        pass

            threading.Thread(target=feed, daemon=True).start()
            os.dup2(read_end, 0)
            os.close(read_end)
        else:
            devnull = os.open(os.devnull, os.O_RDONLY)
            os.dup2(devnull, 0)
        sys.stdin = open(0, closefd=False)
        signal.signal(signal.SIGPIPE, signal.SIG_IGN)
        from imufdi_cli.cli import main

        code = 0
        try:
            main(argv)
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    except BaseException:
        import traceback

        traceback.print_exc()
        sys.stderr.flush()
        os._exit(99)


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


class Runner:
    """Runs commands in forked children, at most ``jobs`` at a time."""

    def __init__(self, jobs: int, timeout: float) -> None:
        self.jobs = jobs
        self.timeout = timeout
        self.running: dict[int, tuple[float, dict]] = {}
        self.done: list[Outcome] = []
        self.pending: collections.Counter = collections.Counter()  # runs left per input
        self.keep_inputs = False

    def submit(self, spec: dict) -> None:
        while len(self.running) >= self.jobs:
            self._reap(block=True)
        sys.stdout.flush()
        sys.stderr.flush()
        pid = os.fork()
        if pid == 0:
            _child(
                spec["argv"],
                spec["stdin"],
                spec["out_dir"],
                spec.get("stdin_path"),
                spec.get("stdout"),
            )
        self.running[pid] = (time.monotonic(), spec)

    def _reap(self, block: bool) -> None:
        while True:
            for pid, (started, spec) in list(self.running.items()):
                waited, status, usage = os.wait4(pid, os.WNOHANG)
                if waited == 0:
                    if time.monotonic() - started > self.timeout:
                        os.kill(pid, signal.SIGKILL)
                        _, status, usage = os.wait4(pid, 0)
                        self._finish(spec, None, usage.ru_maxrss)
                        del self.running[pid]
                    continue
                code = os.waitstatus_to_exitcode(status)
                self._finish(spec, code, usage.ru_maxrss)
                del self.running[pid]
            if not block or len(self.running) < self.jobs:
                return
            time.sleep(0.01)

    def drain(self) -> None:
        while self.running:
            self._reap(block=False)
            time.sleep(0.01)

    def _finish(self, spec: dict, code: int | None, rss_kb: int) -> None:
        out_dir: Path = spec["out_dir"]
        stderr = (out_dir / "stderr").read_text(errors="replace")
        kept = {"stdout", "stderr", *spec.get("made", ()), *spec.get("own", ())}
        names = sorted(p.name for p in out_dir.iterdir() if p.name not in kept)
        leftovers = [n for n in names if n not in spec["outputs"]]
        after_failure = [n for n in names if n in spec["outputs"]] if code != 0 else []
        modified = any(_sha(path) != digest for path, digest in spec["watched"].items())
        self.pending[spec["input"]] -= 1
        if self.pending[spec["input"]] == 0 and not self.keep_inputs and spec.get("own") is None:
            spec["input"].unlink()
        self.done.append(
            Outcome(
                spec["command"],
                spec["input"].name,
                spec["mutation"],
                spec["stdin"] is not None,
                code,
                stderr,
                rss_kb,
                modified,
                leftovers,
                after_failure,
                spec.get("expect_exit"),
            )
        )
        shutil.rmtree(out_dir, ignore_errors=True)


# --- classification -----------------------------------------------------------------------


def _message_problems(stderr: str) -> tuple[bool, bool]:
    """(an empty error/warning message, an error message over several lines)."""
    lines = [line for line in stderr.splitlines() if line.strip()]
    empty = False
    for line in lines:
        for prefix in ("imufdi: error:", "warning:"):
            if line.startswith(prefix):
                text = line[len(prefix) :].strip()
                if not text or text.endswith(":"):
                    empty = True
    errors = [i for i, line in enumerate(lines) if line.startswith("imufdi: error:")]
    multi = bool(errors) and any(
        not (line.startswith("imufdi: error:") or line.startswith("warning:"))
        for line in lines[errors[0] + 1 :]
    )
    return empty, multi


def summarize(outcomes: list[Outcome], parent_rss_kb: int) -> dict:
    commands = [*COMMANDS, *sorted({o.command for o in outcomes} - set(COMMANDS))]
    per_command: dict[str, collections.Counter] = {c: collections.Counter() for c in commands}
    examples: dict[str, list[str]] = collections.defaultdict(list)
    peak = {c: 0 for c in commands}
    for o in outcomes:
        counts = per_command[o.command]
        counts["runs"] += 1
        counts[f"exit {o.exit_code}" if o.exit_code is not None else "hang"] += 1
        peak[o.command] = max(peak[o.command], o.peak_rss_kb)
        empty, multi = _message_problems(o.stderr)
        flags = {
            "traceback": "Traceback" in o.stderr,
            "empty message": empty,
            "multi-line error": multi,
            "exit 4": o.exit_code == 4,
            "hang": o.exit_code is None,
            "input modified": o.input_modified,
            "leftover files": bool(o.leftovers),
            "output after failure": bool(o.outputs_after_failure),
            "rss > 512 MB": o.peak_rss_kb > 512 * 1024,
            "alias not refused": o.expect_exit is not None and o.exit_code != o.expect_exit,
        }
        for name, bad in flags.items():
            if bad:
                counts[name] += 1
                if len(examples[name]) < 5:
                    last = (o.stderr.strip().splitlines() or [""])[-1][:300]
                    examples[name].append(
                        f"{o.command}{' (stdin)' if o.stdin else ''} {o.file} [{o.mutation}]"
                        f" exit={o.exit_code} leftovers={o.leftovers or o.outputs_after_failure}"
                        f" :: {last}"
                    )
    messages: collections.Counter = collections.Counter()
    for o in outcomes:
        for line in o.stderr.splitlines():
            if line.startswith(("imufdi: error:", "warning:")):
                # the message without numbers and file names: one entry per kind
                words = [w for w in line.split() if not any(ch.isdigit() for ch in w)]
                messages[f"{o.command} exit {o.exit_code}: {' '.join(words)[:110]}"] += 1
    total: collections.Counter = collections.Counter()
    for counts in per_command.values():
        total.update(counts)
    return {
        "per_command": {c: dict(v) for c, v in per_command.items()},
        "total": dict(total),
        "peak_rss_mb": {c: round(v / 1024, 1) for c, v in peak.items()},
        "parent_rss_mb": round(parent_rss_kb / 1024, 1),
        "examples": dict(examples),
        "messages": dict(messages.most_common()),
    }


def _print(report: dict, elapsed: float, n_files: int, verbose: bool) -> None:
    commands = list(report["per_command"])
    keys = [
        "runs",
        "exit 0",
        "exit 1",
        "exit 2",
        "exit 3",
        "exit 4",
        "hang",
        "traceback",
        "empty message",
        "multi-line error",
        "input modified",
        "leftover files",
        "output after failure",
        "rss > 512 MB",
        "alias not refused",
    ]
    print(f"{n_files} mutated files, {report['total'].get('runs', 0)} runs, {elapsed:.0f} s")
    print(f"{'':22}" + "".join(f"{c:>10}" for c in (*commands, "total")))
    for key in keys:
        row = [report["per_command"][c].get(key, 0) for c in commands]
        print(f"{key:22}" + "".join(f"{v:>10}" for v in (*row, report["total"].get(key, 0))))
    print(
        f"{'peak RSS (MB)':22}"
        + "".join(f"{report['peak_rss_mb'][c]:>10}" for c in commands)
        + f"   (forked from a parent of {report['parent_rss_mb']} MB)"
    )
    for name, lines in report["examples"].items():
        print(f"\n{name}:")
        for line in lines:
            print(f"  {line}")
    if verbose:
        print("\nmessages (numbers and names removed), most common first:")
        for text, count in report["messages"].items():
            print(f"{count:6}  {text}")


def fuzz(
    workdir: Path,
    *,
    files: int,
    seed: int = 1,
    jobs: int = 2,
    timeout: float = 60.0,
    families: Sequence[str] = FAMILIES,
    keep_inputs: bool = False,
    bases: dict[str, Path] | None = None,
) -> dict:
    """Make ``files`` mutated inputs (the ``families`` in turn) in ``workdir``, run them
    through the commands, and return :func:`summarize`'s report (plus ``bases_modified``:
    base files a run changed). ``bases`` (from :func:`build_bases`) are built in
    ``workdir`` when not given."""
    for family in families:
        if family not in FAMILIES:
            raise ValueError(f"unknown family {family!r}; valid: {', '.join(FAMILIES)}")
    if bases is None:
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            bases = build_bases(workdir)
    base_bytes = {name: path.read_bytes() for name, path in bases.items()}
    rng = np.random.default_rng(seed)
    runner = Runner(jobs, timeout)
    runner.keep_inputs = keep_inputs
    parent_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    for i in range(files):
        family = families[i % len(families)]
        choices = FAMILY_BASES[family]
        base = choices[(i // len(families)) % len(choices)]
        if family == "aliases":
            out_dir = Path(tempfile.mkdtemp(prefix="alias-", dir=workdir))
            case = ALIAS_CASES[(i // len(families)) % len(ALIAS_CASES)]
            spec = alias_case(bases[base], bases["array"], out_dir, case)
            watched = [spec["input"], *([spec["also"]] if "also" in spec else [])]
            runner.pending[spec["input"]] = 1
            runner.submit(
                {
                    **spec,
                    "stdin": None,
                    "out_dir": out_dir,
                    "outputs": [],
                    "own": sorted(p.name for p in out_dir.iterdir()),
                    "watched": {p: _sha(p) for p in watched},
                    "mutation": f"{base}:alias:{spec['case']}",
                    "expect_exit": 2,
                }
            )
            continue
        path = workdir / f"m{i:05d}-{family}-{base}.mcap"
        if family == "bytes":
            data, how = mutate(base_bytes[base], rng)
            path.write_bytes(data)
        else:
            mutator = {"metadata": mutate_metadata, "numeric": mutate_numeric, "gaps": mutate_gaps}
            how = mutator[family](bases[base], path, rng)
            data = path.read_bytes()
        digest = _sha(path)
        piped = COMMANDS[i % len(COMMANDS)]
        runner.pending[path] = len(COMMANDS)
        for command in COMMANDS:
            out_dir = Path(tempfile.mkdtemp(prefix=f"{command}-", dir=workdir))
            use_stdin = command == piped
            argv, outputs = _argv(command, "-" if use_stdin else str(path), out_dir)
            runner.submit(
                {
                    "argv": argv,
                    "stdin": data if use_stdin else None,
                    "out_dir": out_dir,
                    "outputs": outputs,
                    "command": command,
                    "input": path,
                    "watched": {path: digest},
                    "mutation": f"{family}:{base}:{how}",
                }
            )
    runner.drain()
    report = summarize(runner.done, parent_rss)
    report["bases_modified"] = [n for n, p in bases.items() if p.read_bytes() != base_bytes[n]]
    return report


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--files", type=int, default=1000, help="mutated files (default 1000)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--timeout", type=float, default=60.0, help="seconds before a hang")
    parser.add_argument("--json", action="store_true", help="print the counts as JSON")
    parser.add_argument("--keep", help="keep the base files and mutated inputs here")
    parser.add_argument("-v", "--verbose", action="store_true", help="also list the messages")
    parser.add_argument(
        "--families",
        default=",".join(FAMILIES),
        help=f"mutation families, in turn (default: all: {','.join(FAMILIES)})",
    )
    args = parser.parse_args()
    families = [f for f in args.families.split(",") if f]
    unknown = [f for f in families if f not in FAMILIES]
    if unknown:
        parser.error(f"unknown family {unknown[0]!r}; valid: {', '.join(FAMILIES)}")

    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    import imufdi_cli.cli
    import imufdi_cli.detect
    import imufdi_cli.faults
    import imufdi_cli.pipeline
    import imufdi_cli.report  # noqa: F401

    workdir = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="imufdi-fuzz-"))
    workdir.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    try:
        report = fuzz(
            workdir,
            files=args.files,
            seed=args.seed,
            jobs=args.jobs,
            timeout=args.timeout,
            families=families,
            keep_inputs=bool(args.keep),
        )
    finally:
        if not args.keep:
            shutil.rmtree(workdir, ignore_errors=True)
    for name in report["bases_modified"]:
        print(f"base file {name} was modified", file=sys.stderr)
    elapsed = time.monotonic() - started
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        _print(report, elapsed, args.files, args.verbose)


if __name__ == "__main__":
    main()
