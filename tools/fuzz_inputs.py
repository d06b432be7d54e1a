#!/usr/bin/env python3
"""Mutation fuzz of imufdi's MCAP inputs through the CLI (docs/testing.md, "Fuzzing").

Builds a few small logs (chunked zstd, chunked lz4 with small chunks, un-chunked, and a
detector output), mutates them (bit flips, random bytes, cuts, huge or zero u64 fields,
deleted/duplicated/zeroed ranges; 1-3 mutations stacked), and runs every mutated file
through ``info``, ``detect``, ``inject`` and ``report`` (one of them reading it through a
pipe on stdin). It counts, per command and in total:

- exit codes (4 = internal error),
- tracebacks on stderr, empty error/warning messages (nothing after the colon), error
  messages over more than one line,
- hangs (killed at ``--timeout``),
- peak RSS of each run (from ``wait4``; runs are forked from a parent that has imported
  imufdi, numpy and scipy, as a fresh process would),
- inputs modified by the run, output files left after a failed run, and leftover
  temporary files in the output directory.

Usage::

    PYTHONPATH=. python tools/fuzz_inputs.py --files 1000 --seed 1 --jobs 2

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
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

COMMANDS = ("info", "detect", "inject", "report")
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
    return {"zstd": sim, "lz4": lz4, "unchunked": unchunked, "detected": detected}


# --- mutations ----------------------------------------------------------------------------

_U64 = [0, 1, 2**31, 2**32 - 1, 2**40, 2**63, 2**64 - 1, 77_309_414_278]


def mutate(data: bytes, rng: np.random.Generator) -> tuple[bytes, str]:
    """1-3 stacked mutations; returns the bytes and a short description."""
    out = bytearray(data)
    done = []
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


def _argv(command: str, source: str, out_dir: Path) -> tuple[list[str], list[str]]:
    """CLI arguments and the output files a successful run leaves."""
    if command == "info":
        return ["info", source], []
    if command == "detect":
        return ["detect", source, "-d", "glt", "-o", str(out_dir / "det.mcap")], ["det.mcap"]
    if command == "inject":
        return ["inject", source, "--fault", FAULT, "-o", str(out_dir / "inj.mcap")], ["inj.mcap"]
    return ["report", source, "--json", str(out_dir / "r.json")], ["r.json"]


def _child(argv: list[str], stdin_data: bytes | None, out_dir: Path) -> None:
    """In the forked child: redirect stdio, run the CLI, exit with its code."""
    try:
        os.chdir(out_dir)
        stdout = os.open(out_dir / "stdout", os.O_WRONLY | os.O_CREAT, 0o644)
        stderr = os.open(out_dir / "stderr", os.O_WRONLY | os.O_CREAT, 0o644)
        os.dup2(stdout, 1)
        os.dup2(stderr, 2)
        if stdin_data is not None:
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
            _child(spec["argv"], spec["stdin"], spec["out_dir"])
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
        names = sorted(p.name for p in out_dir.iterdir() if p.name not in ("stdout", "stderr"))
        leftovers = [n for n in names if n not in spec["outputs"]]
        after_failure = [n for n in names if n in spec["outputs"]] if code != 0 else []
        modified = _sha(spec["input"]) != spec["input_sha"]
        self.pending[spec["input"]] -= 1
        if self.pending[spec["input"]] == 0 and not self.keep_inputs:
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
    per_command: dict[str, collections.Counter] = {c: collections.Counter() for c in COMMANDS}
    examples: dict[str, list[str]] = collections.defaultdict(list)
    peak = {c: 0 for c in COMMANDS}
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
    ]
    print(f"{n_files} mutated files, {report['total'].get('runs', 0)} runs, {elapsed:.0f} s")
    print(f"{'':22}" + "".join(f"{c:>9}" for c in (*COMMANDS, "total")))
    for key in keys:
        row = [report["per_command"][c].get(key, 0) for c in COMMANDS]
        print(f"{key:22}" + "".join(f"{v:>9}" for v in (*row, report["total"].get(key, 0))))
    print(
        f"{'peak RSS (MB)':22}"
        + "".join(f"{report['peak_rss_mb'][c]:>9}" for c in COMMANDS)
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--files", type=int, default=1000, help="mutated files (default 1000)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--timeout", type=float, default=60.0, help="seconds before a hang")
    parser.add_argument("--json", action="store_true", help="print the counts as JSON")
    parser.add_argument("--keep", help="keep the base files and mutated inputs here")
    parser.add_argument("-v", "--verbose", action="store_true", help="also list the messages")
    args = parser.parse_args()

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
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            bases = build_bases(workdir)
        base_bytes = {name: path.read_bytes() for name, path in bases.items()}
        rng = np.random.default_rng(args.seed)
        runner = Runner(args.jobs, args.timeout)
        runner.keep_inputs = bool(args.keep)
        parent_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        names = sorted(bases)
        for i in range(args.files):
            base = names[i % len(names)]
            data, how = mutate(base_bytes[base], rng)
            path = workdir / f"m{i:05d}-{base}.mcap"
            path.write_bytes(data)
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
                        "input_sha": digest,
                        "mutation": f"{base}:{how}",
                    }
                )
        runner.drain()
        for name, path in bases.items():
            if path.read_bytes() != base_bytes[name]:
                print(f"base file {name} was modified", file=sys.stderr)
        report = summarize(runner.done, parent_rss)
    finally:
        if not args.keep:
            shutil.rmtree(workdir, ignore_errors=True)
    elapsed = time.monotonic() - started
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        _print(report, elapsed, args.files, args.verbose)


if __name__ == "__main__":
    main()
