"""Campaign scaling: ``imufdi campaign`` with ``--jobs 2`` against ``--jobs 1`` on
docs/campaigns/compare.toml, wall time and steady-state throughput, as ratios in one run.

The work is the reference spec itself (every base, fault and detector of compare.toml)
on its first ``--seeds`` evaluation seeds (default 1: 45 runs when written, from 36 ms
conical6 runs to cnn-map runs of about 40 s; ``--skip`` leaves detectors out). Each pass is the real command in a fresh process::

    python -m imufdi_cli campaign SPEC -o DIR --jobs J

so its wall time includes interpreter start-up, imports, spec loading, pool start and the
summary files. Figures:

- **wall**: seconds of each command, and ``wall(--jobs 1) / wall(--jobs 2)``;
- **cores available**: before the passes, what one and two busy-looping processes of
  this process's (setsid) session get (the machine's bound on any speed-up at that moment);
- **pool start**: starting and stopping a 2-worker pool in this process, forked (now)
  and spawned (before), in wall and CPU seconds;
- **CPU**: user + system seconds of the command and its workers; ``CPU / wall`` is how
  many cores the pass actually got, and ``CPU(--jobs 2) / CPU(--jobs 1)`` what the pool
  costs in work (1.0 = nothing);
- **steady**: work done per second between the moments 10 % and 90 % of the work had
  finished, read from the modification times of ``runs/<key>.json`` (written when each run
  ends). Runs differ by 400x in cost, so a run counts as its own cost: its seconds in the
  ``--jobs 1`` pass (the same weights for both passes). The ratio is the 2-worker rate over
  the 1-worker rate; start-up, the last runs' tail and the summary are outside the window.

Passes alternate ``--jobs 1, --jobs 2`` (``--rounds``, ABBA order from two rounds on) so
that a load change on the shared machine hits both; the load average is printed before
and after. On a machine shared with other sessions the wall figures depend on the cores
left free: Linux's autogroup scheduler gives each session a fair share of the CPU however
many processes it runs, so a saturated machine gives ``--jobs 2`` no more CPU than
``--jobs 1`` (the "cores busy" figure shows it). The outputs of all passes must be
byte-identical (checked). Run::

    python benchmarks/bench_campaign.py [--seeds 1] [--rounds 1] [--skip woa-mvmd-glt]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SPEC = ROOT / "docs" / "campaigns" / "compare.toml"


def subset_spec(seeds: int, skip: list[str]) -> str:
    """compare.toml with its first ``seeds`` seeds and without the ``skip`` detectors."""
    text = SPEC.read_text(encoding="utf-8")
    match = re.search(r"^seeds = \[([^\]]*)\]", text, flags=re.M)
    assert match, "compare.toml has no seeds list"
    values = [int(v) for v in match.group(1).replace("\n", " ").split(",") if v.strip()]
    text = text[: match.start()] + f"seeds = {values[:seeds]}" + text[match.end() :]
    for name in skip:
        text, count = re.subn(
            r'\[\[detector\]\][^\n]*\n(?:bases = [^\n]*\n)?name = "'
            + re.escape(name)
            + r'"[^\n]*\n'
            r"(?:params = [^\n]*\n)?",
            "",
            text,
        )
        assert count, f"no detector {name!r} in {SPEC}"
    return text


def cpu_of_children() -> float:
    """User + system CPU seconds of every finished (and waited-for) descendant."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def one_pass(
    spec: Path, out: Path, jobs: int
) -> tuple[float, float, dict[str, float], dict[str, float]]:
    """Run the command; (wall s, CPU s of the command and its workers, finish time per
    run key, run seconds per key)."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    command = [sys.executable, "-m", "imufdi_cli", "campaign", str(spec), "-o", str(out)]
    start_wall = time.time()
    cpu = cpu_of_children()
    start = time.perf_counter()
    subprocess.run([*command, "--jobs", str(jobs)], check=True, env=env, capture_output=True)
    wall = time.perf_counter() - start
    cpu = cpu_of_children() - cpu
    finished: dict[str, float] = {}
    seconds: dict[str, float] = {}
    for path in (out / "runs").glob("*.json"):
        finished[path.stem] = path.stat().st_mtime - start_wall
        seconds[path.stem] = float(json.loads(path.read_text())["seconds"])
    return wall, cpu, finished, seconds


def steady_rate(finished: dict[str, float], weight: dict[str, float]) -> float:
    """Work (weight seconds) finished per second between 10 % and 90 % of the work."""
    order = sorted(finished, key=finished.__getitem__)
    total = sum(weight[k] for k in order)
    done = 0.0
    marks: dict[float, tuple[float, float]] = {}
    for key in order:
        done += weight[key]
        for q in (0.1, 0.9):
            if q not in marks and done >= q * total:
                marks[q] = (done, finished[key])
    (w0, t0), (w1, t1) = marks[0.1], marks[0.9]
    return (w1 - w0) / (t1 - t0)


def cores_available(processes: int, seconds: float = 5.0) -> float:
    """Cores that ``processes`` busy-looping processes of this (setsid) session got together over
    ``seconds`` (CPU seconds / wall seconds): with 2 idle cores, 1.0 for one and 2.0 for
    two; on a machine saturated by other sessions, the session's share either way."""
    cpu = cpu_of_children()
    loop = f"import time\nt = time.time()\nwhile time.time() - t < {seconds}: pass"
    procs = [subprocess.Popen([sys.executable, "-c", loop]) for _ in range(processes)]
    for proc in procs:
        proc.wait()
    return (cpu_of_children() - cpu) / seconds


def pool_start(spec: Path) -> None:
    """Start and stop a 2-worker pool in this process, forked and spawned (the former
    method), after loading the spec as the command does: wall and CPU."""
    from imufdi_cli.campaign import load_spec
    from imufdi_cli.campaign.executors import LocalExecutor

    load_spec(spec)
    for method in ("fork", "spawn"):
        usage = resource.getrusage(resource.RUSAGE_SELF)
        cpu = usage.ru_utime + usage.ru_stime + cpu_of_children()
        start = time.perf_counter()
        executor = LocalExecutor(2, method=method)
        executor.start(10)
        wall = time.perf_counter() - start
        executor.close()
        usage = resource.getrusage(resource.RUSAGE_SELF)
        cpu = usage.ru_utime + usage.ru_stime + cpu_of_children() - cpu
        print(f"pool start, 2 workers, {method:5s}: {wall:5.2f} s wall, {cpu:4.2f} s CPU")


def load() -> str:
    return ", ".join(f"{x:.1f}" for x in os.getloadavg())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=1, help="first N seeds of compare.toml")
    parser.add_argument("--rounds", type=int, default=1, help="pairs of passes (ABBA order)")
    parser.add_argument("--skip", action="append", default=[], help="leave a detector out")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        spec = Path(tmp) / "compare.toml"
        spec.write_text(subset_spec(args.seeds, args.skip))
        order = [1, 2]
        plan = [j for r in range(args.rounds) for j in (order if r % 2 == 0 else order[::-1])]
        print(
            f"docs/campaigns/compare.toml, first {args.seeds} seed(s)"
            + (f", without {', '.join(args.skip)}" if args.skip else "")
            + f"; cores {os.cpu_count()}; passes {plan}; load average before: {load()}"
        )
        one, two = cores_available(1), cores_available(2)
        print(
            f"cores this session gets now: {one:.2f} for 1 busy process, {two:.2f} for 2"
            " (the bound on any speed-up here: 2 processes need 2 free cores)"
        )
        walls: dict[int, list[float]] = {1: [], 2: []}
        cpus: dict[int, list[float]] = {1: [], 2: []}
        passes: list[tuple[int, dict[str, float]]] = []
        weight: dict[str, float] = {}
        reference: bytes | None = None
        for index, jobs in enumerate(plan):
            out = Path(tmp) / f"out{index}"
            wall, cpu, finished, seconds = one_pass(spec, out, jobs)
            csv = (out / "runs.csv").read_bytes()
            assert reference is None or csv == reference, "runs.csv differs between passes"
            reference = csv
            if jobs == 1 and not weight:
                weight = seconds
            walls[jobs].append(wall)
            cpus[jobs].append(cpu)
            passes.append((jobs, finished))
            print(
                f"  --jobs {jobs}: {len(finished)} runs, wall {wall:6.1f} s, CPU {cpu:6.1f} s"
                f" ({cpu / wall:.2f} cores busy; load {load()})"
            )
        rates: dict[int, list[float]] = {1: [], 2: []}
        for jobs, finished in passes:
            rates[jobs].append(steady_rate(finished, weight))
        wall1, wall2 = (sum(walls[j]) / len(walls[j]) for j in (1, 2))
        rate1, rate2 = (sum(rates[j]) / len(rates[j]) for j in (1, 2))
        work = sum(weight.values())
        print(f"work: {work:.1f} s of runs at --jobs 1 ({len(weight)} runs)")
        print(f"steady (10-90 % of the work): --jobs 1 {rate1:.2f}, --jobs 2 {rate2:.2f} s/s")
        cpu1, cpu2 = (sum(cpus[j]) / len(cpus[j]) for j in (1, 2))
        print(
            f"speed-up --jobs 2 vs --jobs 1: {rate2 / rate1:.2f}x steady, {wall1 / wall2:.2f}x wall"
        )
        print(
            f"CPU of --jobs 2 / --jobs 1: {cpu2 / cpu1:.2f}x (the pool's own cost; the wall"
            " speed-up is bounded by the cores the machine leaves free: see docs/campaign.md)"
        )
        pool_start(spec)
        print(f"load average after: {load()}")


if __name__ == "__main__":
    main()
