"""Benchmark: the commands users wait for, as multiples of ``imufdi info`` on the same log.

Every figure is a ratio of CPU seconds (user + system of the whole command: interpreter
start, imports, every thread) against ``imufdi info`` measured in the same run, the
minimum over ``--repeat`` interleaved rounds (one run of every command per round, so that
a change of load hits all of them alike); the load average is printed with each round.

Logs (made at run time, simulation seed 1, a tuning seed): paper-table4 with 16 IMUs for
``--minutes`` (10 by default) with a 0.9 deg/s gyro step, a 1 deg/s^2 drift and 5 Hz
spikes injected, the same preset for 1 minute, and, for memory, 2-minute logs of 16 and
64 IMUs. Targets (docs/performance.md):

- ``detect -d glt`` (per-sample, explanations on) <= 2.0x ``info``; ``--no-explain``
  <= 1.3x; ``--false-alarms 1/h`` (explanations on) <= 1.3x;
- ``report`` of the detected log <= 0.8x ``info`` of the input;
- a 1-minute ``report`` <= 1.5x ``info`` of the same log (start-up);
- ``detect -d glt`` peak memory from 16 to 64 IMUs <= 2x.

Every command that writes a file writes a new one (the previous round's output is
removed before the command starts, outside its time), as at a first run.

Bytecode: by default the children read compiled bytecode from a cache directory made
once (as after ``pip install``); ``--cold`` compiles every project module at each start
(a checkout run with ``PYTHONDONTWRITEBYTECODE=1``). ``--baseline TREE`` also runs every
command from another checkout (e.g. ``git worktree add /tmp/base main``), interleaved, and
prints this tree's CPU over the baseline's.

    python benchmarks/bench_targets.py                     # 10-minute log, 3 rounds
    python benchmarks/bench_targets.py --minutes 3 --repeat 5 --skip-memory
    python benchmarks/bench_targets.py --baseline /tmp/base
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
TREE = HERE.parent

#: (name, command after ``imufdi``, target as a multiple of its info, info it divides by)
COMMANDS: list[tuple[str, list[str], float | None, str]] = [
    ("info", ["info", "{log}"], None, "info"),
    ("detect", ["detect", "-d", "glt", "{log}", "-o", "{out}/explained.mcap"], 2.0, "info"),
    (
        "detect --no-explain",
        ["detect", "-d", "glt", "--no-explain", "{log}", "-o", "{out}/unexplained.mcap"],
        1.3,
        "info",
    ),
    (
        "detect --false-alarms 1/h",
        ["detect", "-d", "glt", "--false-alarms", "1/h", "{log}", "-o", "{out}/budget.mcap"],
        1.3,
        "info",
    ),
    ("report", ["report", "{out}/explained.mcap"], 0.8, "info"),
    ("info (1 min)", ["info", "{short}"], None, "info (1 min)"),
    (
        "detect (1 min)",
        ["detect", "-d", "glt", "{short}", "-o", "{out}/short.mcap"],
        None,
        "info (1 min)",
    ),
    ("report (1 min)", ["report", "{out}/short.mcap"], 1.5, "info (1 min)"),
]

FAULTS = [
    "step:imu3.gyro.x,at={a:.1f}s,amp=0.9deg/s",
    "drift:imu7.gyro.y,at={b:.1f}s,rate=1deg/s^2,duration=60s",
    "spikes:imu11.gyro.z,at={c:.1f}s,duration=60s,rate=5Hz,amp=3deg/s",
]


def load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


class Runner:
    """Runs ``imufdi`` commands of one tree in fresh processes and measures them."""

    def __init__(self, tree: Path, pycache: Path | None) -> None:
        self.tree = tree
        self.env = dict(
            os.environ,
            PYTHONPATH=str(tree),
            OPENBLAS_NUM_THREADS="1",
            OMP_NUM_THREADS="1",
            MKL_NUM_THREADS="1",
        )
        if pycache is not None:
            self.env.pop("PYTHONDONTWRITEBYTECODE", None)
            self.env["PYTHONPYCACHEPREFIX"] = str(pycache)
        else:
            self.env["PYTHONDONTWRITEBYTECODE"] = "1"

    def run(self, args: list[str]) -> tuple[float, float, float]:
        """(CPU s, wall s, peak RSS MiB) of ``python -m imufdi_cli ARGS`` (output discarded)."""
        return self.run_python(["-m", "imufdi_cli", *args])

    def run_python(self, args: list[str]) -> tuple[float, float, float]:
        """(CPU s, wall s, peak RSS MiB) of ``python ARGS`` in the tree (output discarded)."""
        start = time.perf_counter()
        process = subprocess.Popen(
            [sys.executable, *args],
            env=self.env,
            # ``-m`` puts the working directory first on sys.path: run in the tree, so that
            # each tree imports its own package
            cwd=self.tree,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
        )
        _, status, usage = os.wait4(process.pid, 0)
        wall = time.perf_counter() - start
        process.returncode = os.waitstatus_to_exitcode(status)
        stderr = process.stderr.read().decode() if process.stderr else ""
        if process.stderr:
            process.stderr.close()
        if process.returncode not in (0, 1):
            raise RuntimeError(f"python {' '.join(args)} failed ({process.returncode}):\n{stderr}")
        return usage.ru_utime + usage.ru_stime, wall, usage.ru_maxrss / 1024


def make_log(runner: Runner, workdir: Path, minutes: float, key: str = "log") -> Path:
    """The faulty paper-table4 log of ``minutes`` (seed 1), ``faulty-KEY.mcap``."""
    clean = workdir / f"clean-{key}.mcap"
    faulty = workdir / f"faulty-{key}.mcap"
    seconds = minutes * 60
    runner.run(
        [
            *("simulate", "--preset", "paper-table4", "--duration", f"{seconds:g}s"),
            *("--seed", "1", "-o", str(clean), "-q"),
        ]
    )
    times = {"a": 0.3 * seconds, "b": 0.5 * seconds, "c": 0.7 * seconds}
    faults = [arg for f in FAULTS for arg in ("--fault", f.format(**times))]
    runner.run(["inject", str(clean), *faults, "--seed", "1", "-o", str(faulty), "-q"])
    clean.unlink()
    return faulty


def make_logs(runner: Runner, workdir: Path, minutes: float) -> dict[str, Path]:
    """The faulty paper-table4 logs of ``minutes`` and of 1 minute."""
    return {
        key: make_log(runner, workdir, length, key)
        for key, length in (("log", minutes), ("short", 1.0))
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--minutes", type=float, default=10.0, help="length of the main log")
    parser.add_argument("--repeat", type=int, default=3, help="interleaved rounds (min kept)")
    parser.add_argument("--cold", action="store_true", help="compile the modules at each start")
    parser.add_argument("--baseline", type=Path, help="another checkout, run interleaved")
    parser.add_argument("--skip-memory", action="store_true", help="no 16 vs 64 IMU memory")
    parser.add_argument("--only", help="comma-separated command names to run (and info)")
    parser.add_argument("--dir", type=Path, help="where to put the logs (default: temporary)")
    args = parser.parse_args()
    workdir = Path(args.dir or tempfile.mkdtemp(prefix="imufdi-bench-targets-")).resolve()
    workdir.mkdir(parents=True, exist_ok=True)
    trees = {"this": TREE}
    if args.baseline is not None:
        trees["baseline"] = args.baseline.resolve()
    runners = {
        name: Runner(tree, None if args.cold else workdir / f"pycache-{name}")
        for name, tree in trees.items()
    }
    print(f"load average before: {load()} ({os.cpu_count()} cores)")
    print(
        f"bytecode: {'compiled at every start' if args.cold else 'warm (compiled once, cached)'};"
        f" trees: {', '.join(f'{k} = {v}' for k, v in trees.items())}"
    )
    logs = make_logs(runners["this"], workdir, args.minutes)
    commands = COMMANDS
    if args.only:
        wanted = {name.strip() for name in args.only.split(",")}
        prerequisites = {"report": "detect", "report (1 min)": "detect (1 min)"}
        wanted |= {prerequisites[n] for n in wanted if n in prerequisites}
        wanted |= {base for name, _, _, base in COMMANDS if name in wanted}
        commands = [c for c in COMMANDS if c[0] in wanted]
    outputs = {name: workdir / f"out-{name}" for name in trees}
    for out in outputs.values():
        out.mkdir(exist_ok=True)
    print(
        f"logs: paper-table4, 16 IMUs, 100 Hz: {args.minutes:g} min"
        f" ({logs['log'].stat().st_size / 1e6:.0f} MB) and 1 min, faults injected"
    )
    cpu: dict[tuple[str, str], list[float]] = {}
    wall: dict[tuple[str, str], list[float]] = {}
    peak: dict[tuple[str, str], float] = {}
    for round_index in range(args.repeat):
        for name, runner in runners.items():
            for command, template, _, _ in commands:
                argv = [
                    part.format(log=logs["log"], short=logs["short"], out=outputs[name])
                    for part in template
                ]
                if "-o" in argv:
                    # a fresh output, as at a first run: replacing last round's file would
                    # add the file system's release of its blocks (about 0.06 s of system
                    # CPU for the 117 MB of a 10-minute detect) to the command's time
                    Path(argv[argv.index("-o") + 1]).unlink(missing_ok=True)
                seconds, elapsed, rss = runner.run(argv)
                key = (name, command)
                cpu.setdefault(key, []).append(seconds)
                wall.setdefault(key, []).append(elapsed)
                peak[key] = max(peak.get(key, 0.0), rss)
        print(f"round {round_index + 1}/{args.repeat} done, load average {load()}")
    for name in trees:
        print(f"\n{name} tree ({trees[name]}): CPU s (min of {args.repeat}), ratio, target")
        for command, _, target, base in commands:
            key = (name, command)
            best = min(cpu[key])
            ratio = best / min(cpu[(name, base)])
            paired = statistics.median(
                c / b for c, b in zip(cpu[key], cpu[(name, base)], strict=True)
            )
            verdict = ""
            if target is not None:
                verdict = f"target <= {target:g}x: {'met' if ratio <= target else 'NOT met'}"
            print(
                f"  {command:27s} CPU {best:6.2f} s  wall {min(wall[key]):6.2f} s"
                f"  peak {peak[key]:6.0f} MiB  = {ratio:5.2f}x {base:12s}"
                f" (median of rounds {paired:5.2f}x)  {verdict}"
            )
    if "baseline" in trees:
        print("\nthis tree / baseline (CPU, min of each):")
        for command, _, _, _ in commands:
            ratio = min(cpu[("this", command)]) / min(cpu[("baseline", command)])
            print(f"  {command:27s} {ratio:5.2f}x")
    if not args.skip_memory:
        print(f"\ndetect -d glt peak memory by IMU count (2-minute logs; load {load()}):")
        for name, runner in runners.items():
            peaks = {}
            for imus in (16, 64):
                path = workdir / f"imus{imus}.mcap"
                if not path.exists():
                    runners["this"].run(
                        [
                            *("simulate", "--preset", "paper-table4", "--imus", str(imus)),
                            *("--duration", "120s", "--seed", "1", "-o", str(path), "-q"),
                        ]
                    )
                runs = [
                    runner.run(
                        ["detect", "-d", "glt", str(path), "-o", str(outputs[name] / "m.mcap")]
                    )
                    for _ in range(2)
                ]
                peaks[imus] = min(r[2] for r in runs)
            ratio = peaks[64] / peaks[16]
            print(
                f"  {name}: 16 IMUs {peaks[16]:.0f} MiB, 64 IMUs {peaks[64]:.0f} MiB:"
                f" {ratio:.2f}x for 4x the IMUs (target <= 2x: {'met' if ratio <= 2 else 'NOT met'})"
            )
    print(f"\nload average after: {load()}")
    if not args.dir:
        shutil.rmtree(workdir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
