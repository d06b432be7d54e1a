"""Run every benchmark in this folder, one after the other, and print their figures.

Each ``bench_*.py`` prints its own figures and ratios against a peer or baseline measured
in the same run (never a fixed number of seconds). This runner only sequences them, so
that they do not compete for the 2 cores, and prints a one-line status per script.

    python benchmarks/run.py              # all, with each script's defaults (full targets)
    python benchmarks/run.py --quick      # smaller inputs, a few minutes in all
    python benchmarks/run.py glt read     # only bench_glt.py and bench_read.py
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent

#: smaller inputs for --quick (the ratios are still measured in the same run)
QUICK: dict[str, list[str]] = {
    "detect": ["--minutes", "5", "--long-factor", "10"],
    "ingest": ["--mb", "20", "--memory-mb", "5"],
    "read": ["--samples", "62500"],
    "mvmd": ["--seeds", "3"],
    "noise_glr": ["--seeds", "5"],
    "bank": ["--duration", "30"],
    "report": ["--minutes", "1"],
    "events": ["--events", "5000"],
    "woa": ["--duration", "10"],
    "calibrate": ["--factor", "3", "--repeat", "1"],
    "mcap_package": ["--seconds", "10", "--long-minutes", "2"],
    "fclog": ["--seconds", "10", "--repeat", "1"],
    "checksum": ["--frames", "2000", "--repeat", "2"],
}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("names", nargs="*", help="benchmarks to run (default: all)")
    parser.add_argument("--quick", action="store_true", help="smaller inputs")
    args = parser.parse_args()
    scripts = sorted(HERE.glob("bench_*.py"))
    if args.names:
        wanted = {n.removeprefix("bench_").removesuffix(".py") for n in args.names}
        scripts = [s for s in scripts if s.stem.removeprefix("bench_") in wanted]
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    failures = 0
    for script in scripts:
        name = script.stem.removeprefix("bench_")
        extra = QUICK.get(name, []) if args.quick else []
        print(f"\n=== {script.name} {' '.join(extra)}", flush=True)
        start = time.perf_counter()
        done = subprocess.run([sys.executable, str(script), *extra], env=env, check=False)
        status = "ok" if done.returncode == 0 else f"FAILED (exit {done.returncode})"
        failures += done.returncode != 0
        print(f"=== {script.name}: {status} in {time.perf_counter() - start:.1f} s", flush=True)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
