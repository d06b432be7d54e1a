"""Benchmark: ``imufdi detect -d glt`` end to end against ``imufdi info`` on the same log.

Targets (16-IMU, 100 Hz, 1-hour log; docs/performance.md):
- detect (read, detect, write) at most 1.3x the time of ``imufdi info`` (which
  streams the whole log through the same reader), on a clean log and on a faulty one,
  measured with the default episode explanations and with ``--no-explain``;
- the whole command at least 0.5x the speed of just copying the log with the mcap package
  (``make_reader(...).iter_messages`` -> ``Writer.add_message``);
- peak memory of ``detect`` on a 10x longer log within 10 % of the base one.

Besides wall and process CPU, each run's main-thread CPU is printed as a ratio: detect's
writer compresses and writes on other threads, so with two free cores its wall time
follows the main thread's CPU; on a loaded machine that ratio moves less than the wall's.

The logs are simulated at run time (turntable, 16 co-aligned IMUs); the faulty one has a
gyro step, a drift and spikes injected (``imufdi inject``) so alarms and events are written.
Every measurement runs in a fresh subprocess so that peak RSS (``ru_maxrss``) belongs to
that step alone; each timed step is run ``--repeat`` times and the best kept. The load
average is printed: on a shared machine only the ratios mean something.

    python benchmarks/bench_detect.py                 # 60 min base log, 10x for memory
    python benchmarks/bench_detect.py --minutes 10    # quicker
    python benchmarks/bench_detect.py --minutes 10 --stages --skip-memory --skip-copy
                                                      # + detect's CPU split by stage
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

CHILD = textwrap.dedent(
    """
    import json, resource, sys, time
    mode, src, dst = sys.argv[1], sys.argv[2], sys.argv[3]
    start = time.perf_counter()
    cpu = time.process_time()
    main_cpu = time.thread_time()
    if mode in ("detect", "detect-no-explain"):
        from imufdi_cli.detect import detect_file
        detect_file(src, dst, [("glt", {})], explain=mode == "detect")
    elif mode == "stages":
        split = stages(src, dst)
    elif mode == "compile":
        import imufdi_cli.detect, imufdi_cli.episodes, imufdi_cli.faults, imufdi_cli.pipeline
        from imufdi_cli.detectors import make_detectors
        make_detectors([("glt", {})])
    elif mode == "info":
        from imufdi_cli.pipeline import log_info
        log_info(src)
    elif mode == "inject":
        from imufdi_cli.faults import inject_file
        minutes = float(dst.split("@")[1])
        at = [minutes * 60 * f for f in (0.3, 0.5, 0.7)]
        inject_file(src, dst.split("@")[0], [
            f"step:imu3.gyro.x,at={at[0]:.1f}s,amp=0.9deg/s",
            f"drift:imu7.gyro.y,at={at[1]:.1f}s,rate=1deg/s^2,duration=60s",
            f"spikes:imu11.gyro.z,at={at[2]:.1f}s,duration=60s,rate=5Hz,amp=3deg/s",
        ], [], seed=1)
    elif mode == "mcap-copy":
        from mcap.reader import make_reader
        from mcap.writer import Writer
        with open(src, "rb") as f, open(dst, "wb") as g:
            reader = make_reader(f)
            writer = Writer(g)
            writer.start()
            summary = reader.get_summary()
            schemas = {sid: writer.register_schema(s.name, s.encoding, s.data)
                       for sid, s in summary.schemas.items()}
            channels = {cid: writer.register_channel(c.topic, c.message_encoding,
                                                     schemas.get(c.schema_id, 0), c.metadata)
                        for cid, c in summary.channels.items()}
            for _, channel, message in reader.iter_messages(log_time_order=False):
                writer.add_message(channels[channel.id], message.log_time, message.data,
                                   message.publish_time, message.sequence)
            writer.finish()
    elif mode == "simulate":
        from imufdi_cli.pipeline import simulate_file
        minutes = float(dst.split("@")[1])
        simulate_file(None, dst.split("@")[0], seed=1, options={
            "imus": 16, "rate": "100Hz", "duration": f"{minutes * 60}s", "motion": "turntable"})
    seconds = time.perf_counter() - start
    cpu = time.process_time() - cpu
    main_cpu = time.thread_time() - main_cpu
    peak_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    out = {"seconds": seconds, "cpu": cpu, "main_cpu": main_cpu, "peak_mib": peak_kib / 1024}
    if mode == "stages":
        out["stages"] = split
    print(json.dumps(out))
    """
)

# Where detect's CPU goes: wrappers around its stages, each charged its own CPU (process
# CPU time, all threads: the writer's compression threads are charged to whatever the main
# thread was doing), nested stages subtracted from their callers. Imports are timed first.
STAGES = textwrap.dedent(
    """
    def stages(src, dst):
        import collections
        cpu0 = time.process_time()
        from scipy.special import fdtri  # (glt's thresholds; the episode intervals)

        fdtri(1.0, 50.0, 0.99)
        import imufdi_cli.detect as dt
        import imufdi_cli.engine as en
        import imufdi_cli.episodes.builder as ep  # where EpisodeBuilder finds fit_models_batch
        from imufdi_cli.detectors.glt import GltDetector
        acc = collections.Counter({"imports (numpy, imufdi, scipy.special)":
                                   time.process_time() - cpu0})
        active = []

        def wrap(owner, name, key):
            inner = getattr(owner, name)

            def timed(*args, **kwargs):
                begin = time.process_time()
                active.append(key)
                try:
                    return inner(*args, **kwargs)
                finally:
                    active.pop()
                    spent = time.process_time() - begin
                    acc[key] += spent
                    if active:
                        acc[active[-1]] -= spent
            setattr(owner, name, timed)

        wrap(dt._DetectRun, "copy_batch", "copying the input (verbatim chunks, indexes)")
        wrap(en.Engine, "add_block", "conditioner (validity masks, sanitising)")
        wrap(en.Engine, "_fit", "calibration fits (conditioner, glt, builders)")
        wrap(GltDetector, "process", "glt process")
        wrap(dt, "status_records", "status and events: encode, queue, compress")
        wrap(dt, "_events", "status and events: encode, queue, compress")
        wrap(dt.McapWriter, "add_batch", "status and events: encode, queue, compress")
        wrap(ep, "fit_models_batch", "episodes: fit_models")
        wrap(ep.EpisodeBuilder, "rows", "episodes: bookkeeping, residuals, reference")
        wrap(dt._DetectRun, "episodes", "episodes: to_dict and JSON event")
        wrap(dt._DetectRun, "finish", "finish (flush, metadata)")
        begin = time.process_time()
        result = dt.detect_file(src, dst, [("glt", {})])
        total = time.process_time() - begin
        acc["reading and aligning (reader.stream), the rest"] = total - sum(
            v for k, v in acc.items() if not k.startswith("imports"))
        acc["episodes"] = sum(
            sum(s.episodes.values()) for t in result.summaries.values() for s in t.values())
        return dict(acc)
    """
)


#: set by --warm: a bytecode cache directory for the children (else the environment's state)
PYCACHE: list[str] = []


def child(mode: str, src: str, dst: str) -> dict[str, float]:
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    if PYCACHE:
        # warm bytecode, as after ``pip install``: compiled once into this cache, then read
        env.pop("PYTHONDONTWRITEBYTECODE", None)
        env["PYTHONPYCACHEPREFIX"] = PYCACHE[0]
    done = subprocess.run(
        [sys.executable, "-c", STAGES + CHILD, mode, src, dst],
        capture_output=True,
        text=True,
        check=True,
        env=env,
    )
    return json.loads(done.stdout.strip().splitlines()[-1])  # type: ignore[no-any-return]


def best(mode: str, src: str, dst: str, repeat: int) -> dict[str, float]:
    runs = [child(mode, src, dst) for _ in range(repeat)]
    return min(runs, key=lambda r: r["seconds"])


def load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--minutes", type=float, default=60.0, help="base log length")
    parser.add_argument("--long-factor", type=float, default=10.0, help="memory check log length")
    parser.add_argument("--repeat", type=int, default=2, help="runs per timed step (best kept)")
    parser.add_argument("--skip-memory", action="store_true", help="no 10x longer log")
    parser.add_argument("--skip-copy", action="store_true", help="no mcap package copy")
    parser.add_argument("--dir", help="where to put the logs (default: a temporary directory)")
    parser.add_argument(
        "--stages", action="store_true", help="also split detect's CPU by stage (clean log)"
    )
    parser.add_argument(
        "--warm",
        action="store_true",
        help="children read compiled bytecode (as installed) instead of the environment's"
        " state (PYTHONDONTWRITEBYTECODE=1 compiles the project's modules at every start)",
    )
    args = parser.parse_args()
    workdir = Path(args.dir or tempfile.mkdtemp(prefix="imufdi-bench-detect-"))
    workdir.mkdir(parents=True, exist_ok=True)
    base = workdir / "base.mcap"
    faulty = workdir / "faulty.mcap"
    long = workdir / "long.mcap"
    samples = int(args.minutes * 60 * 100)
    print(f"load average before: {load()} ({os.cpu_count()} cores)")
    if args.warm:
        PYCACHE.append(str(workdir / "pycache"))
        child("compile", "-", "-")
    warm = bool(args.warm) or not os.environ.get("PYTHONDONTWRITEBYTECODE")
    print(f"bytecode: {'warm (compiled once, cached)' if warm else 'compiled at every start'}")
    print(
        f"16 IMUs, 100 Hz, {args.minutes:g} min: {samples:,} array samples, "
        f"{samples * 16:,} Imu messages"
    )
    sim = child("simulate", "-", f"{base}@{args.minutes}")  # (also compiles, with --warm)
    print(
        f"simulate + write          {sim['seconds']:8.2f} s  ({base.stat().st_size / 1e6:,.0f} MB)"
    )
    child("inject", str(base), f"{faulty}@{args.minutes}")
    out = str(workdir / "detected.mcap")
    det = {}
    for name, path in (("clean", base), ("faulty", faulty)):
        info = best("info", str(path), "-", args.repeat)
        print(
            f"imufdi info ({name:6s})       {info['seconds']:8.2f} s  CPU {info['cpu']:7.2f} s"
            f"  peak {info['peak_mib']:7.1f} MiB"
        )
        for mode in ("detect", "detect-no-explain"):
            run = best(mode, str(path), out, args.repeat)
            det[(name, mode)] = run
            print(
                f"imufdi {mode:17s}  {run['seconds']:8.2f} s  CPU {run['cpu']:7.2f} s"
                f"  peak {run['peak_mib']:7.1f} MiB"
                f"  = {run['seconds'] / info['seconds']:.2f}x info"
                f" (CPU {run['cpu'] / info['cpu']:.2f}x, main thread CPU"
                f" {run['main_cpu'] / info['main_cpu']:.2f}x)  (target <= 1.3x)"
            )
    base_det = det[("clean", "detect")]
    if args.stages:
        run = child("stages", str(base), out)
        split = run["stages"]
        episodes = int(split.pop("episodes"))
        print(f"detect CPU by stage (clean log, {episodes:,} episodes; load {load()}):")
        for key, value in sorted(split.items(), key=lambda kv: -kv[1]):
            print(f"  {key:52s} {value:7.2f} s  {value / run['cpu']:6.1%}")
        print(f"  {'total':52s} {run['cpu']:7.2f} s")
    print(f"  array samples/s through detect (clean): {samples / base_det['seconds']:,.0f}")
    if not args.skip_copy:
        copy = child("mcap-copy", str(base), str(workdir / "copy.mcap"))
        print(
            f"mcap package copy         {copy['seconds']:8.2f} s  peak {copy['peak_mib']:7.1f} MiB"
        )
        print(
            f"  detect speed vs mcap copy: {copy['seconds'] / base_det['seconds']:.2f}x  (target >= 0.5x)"
        )
    for path in (workdir / "copy.mcap", workdir / "detected.mcap", faulty):
        path.unlink(missing_ok=True)
    if not args.skip_memory:
        long_minutes = args.minutes * args.long_factor
        child("simulate", "-", f"{long}@{long_minutes}")
        det_long = child("detect", str(long), str(workdir / "detected-long.mcap"))
        ratio = det_long["peak_mib"] / base_det["peak_mib"]
        print(
            f"imufdi detect, {long_minutes:g} min  {det_long['seconds']:8.2f} s  "
            f"peak {det_long['peak_mib']:7.1f} MiB"
        )
        print(
            f"  peak memory {args.long_factor:g}x longer log / base: {ratio:.3f}  (target <= 1.10)"
        )
    print(f"load average after: {load()}")
    if not args.dir:
        shutil.rmtree(workdir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
