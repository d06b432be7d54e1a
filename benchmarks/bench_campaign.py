"""Campaign scaling: runs/s with 1 and 2 pool workers, and the executor's per-run overhead.

The work: N runs of the ``paper-table4`` array (16 IMUs, 100 Hz; simulate, inject a gyro
step, GLT, metrics), the same run descriptions for every executor. Figures:

- in-process: :func:`execute_run` called in a loop in this process (the baseline);
- pool, 1 worker / 2 workers: :class:`LocalExecutor` with spawned worker processes
  (``--jobs 1`` on the CLI runs in-process; here the 1-worker pool is forced to isolate the
  executor's cost). Wall time includes pool start (spawning and importing numpy/scipy in
  each worker); the steady rate counts only runs finished after each worker's first one;
- per-run overhead = steady seconds per run with 1 worker - in-process seconds per run.

BLAS is pinned to one thread here and in the workers (``WORKER_THREAD_ENV``), so the
in-process baseline is not penalised by thread fights. Run:
``python benchmarks/bench_campaign.py [--runs 80] [--duration 60s]`` (a 60 s log makes a
run of about 0.1 s, the scale of real detector runs; with 5 s logs of plain GLT a run is
under 10 ms and the fixed cost of shipping results dominates). The figures need idle
cores: the load average is printed.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

for _name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_name] = "1"  # before numpy is imported; the same as WORKER_THREAD_ENV

from imufdi_cli.campaign import WORKER_THREAD_ENV, LocalExecutor, execute_run, load_spec  # noqa: E402

assert all(os.environ[k] == v for k, v in WORKER_THREAD_ENV.items())

SPEC = """
[campaign]
name = "bench"
seeds = [{seeds}]

[[base]]
preset = "paper-table4"
options = {{ duration = "{duration}" }}

[[fault]]
model = "step"
sensor = ["imu0.gyro.x", "imu5.gyro.y"]
at = "2.5s"
amp = ["0.3deg/s", "0.9deg/s"]

[[detector]]
name = "glt"
"""


def timed_pool(runs: list[dict], workers: int) -> tuple[float, float]:
    """(wall seconds including pool start, steady runs/s after each worker's first run)."""
    start = time.perf_counter()
    stamps = []
    for result in LocalExecutor(workers, pool=True).run(runs):
        assert result["ok"], result.get("error")
        stamps.append(time.perf_counter())
    wall = time.perf_counter() - start
    first = stamps[workers - 1]
    steady = (len(stamps) - workers) / (stamps[-1] - first)
    return wall, steady


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=80, help="runs (multiple of 4)")
    parser.add_argument("--duration", default="60s", help="simulated log length per run")
    args = parser.parse_args()
    seeds = ", ".join(str(s) for s in range(max(1, args.runs // 4)))
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bench.toml"
        path.write_text(SPEC.format(seeds=seeds, duration=args.duration))
        runs = load_spec(path).runs
    n = len(runs)
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    print(
        f"{n} runs: paper-table4 (16 IMUs, 100 Hz, {args.duration}), step fault, glt; "
        f"cores: {os.cpu_count()}; load average before: {load}"
    )

    execute_run(runs[0])  # warm imports and caches
    start = time.perf_counter()
    for desc in runs:
        assert execute_run(desc)["ok"]
    in_process = time.perf_counter() - start
    base_rate = n / in_process
    print(f"in-process      : {in_process:6.2f} s  {base_rate:6.2f} runs/s (baseline)")

    wall1, steady1 = timed_pool(runs, 1)
    print(f"pool, 1 worker  : {wall1:6.2f} s  {n / wall1:6.2f} runs/s wall, {steady1:6.2f} steady")
    wall2, steady2 = timed_pool(runs, 2)
    print(f"pool, 2 workers : {wall2:6.2f} s  {n / wall2:6.2f} runs/s wall, {steady2:6.2f} steady")

    print(f"speed-up 2 vs 1 worker : {steady2 / steady1:.2f}x steady, {wall1 / wall2:.2f}x wall")
    print(f"speed-up 2 workers vs in-process: {steady2 / base_rate:.2f}x steady")
    overhead_ms = 1e3 * (1.0 / steady1 - 1.0 / base_rate)
    print(
        f"executor overhead per run: {overhead_ms:+.1f} ms "
        f"({100 * overhead_ms / (1e3 / base_rate):+.1f} % of a {1e3 / base_rate:.0f} ms run); "
        f"pool start + teardown about {wall1 - n / steady1:.1f} s"
    )


if __name__ == "__main__":
    main()
