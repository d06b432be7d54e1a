"""Start-up time of the CLI against ``python -c "import numpy"``, same run.

Usage: python benchmarks/bench_startup.py [--repeat 15]

Every stage of a shell pipeline and every TAB completion pays the CLI's start-up, so it is
measured as a ratio against the floor any numpy tool pays: a fresh interpreter importing
numpy. Each command runs ``--repeat`` times in fresh processes, interleaved so that a
change of machine load hits all of them alike; the median wall time is reported.

Target (issue "Fast where users wait"): ``imufdi --help`` and ``imufdi info small.mcap``
each <= 2x ``python -c "import numpy"``. Also prints which heavy modules (scipy, the
detectors, matplotlib, rich's markdown) ``imufdi --help`` imports: none should be there.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SMALL = ROOT / "sample_logs" / "paper-table4.mcap"


def _time(cmd: list[str]) -> float:
    start = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - start


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeat", type=int, default=15)
    args = parser.parse_args()
    py = sys.executable
    commands = {
        "python -c 'import numpy'": [py, "-c", "import numpy"],
        "imufdi --help": [py, "-m", "imufdi_cli", "--help"],
        "imufdi info small.mcap": [py, "-m", "imufdi_cli", "info", str(SMALL)],
    }
    times: dict[str, list[float]] = {name: [] for name in commands}
    for cmd in commands.values():  # warm the file cache once
        _time(cmd)
    for _ in range(args.repeat):
        for name, cmd in commands.items():
            times[name].append(_time(cmd))
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    print(f"load average: {load} (2-core target machine; ratios, not seconds, are the claim)")
    floor = statistics.median(times["python -c 'import numpy'"])
    for name, values in times.items():
        median = statistics.median(values)
        print(f"{name:28s} median {median * 1000:7.1f} ms   {median / floor:5.2f}x numpy import")
    heavy = ("scipy", "matplotlib", "imufdi_cli.detectors.", "imufdi_cli.campaign", "dask")
    probe = (
        "import runpy, sys\n"
        "sys.argv = ['imufdi', '--help']\n"
        "try:\n    runpy.run_module('imufdi_cli', run_name='__main__')\n"
        "except SystemExit:\n    pass\n"
        f"print(sorted({{m.split('.')[0] if not m.startswith('imufdi') else m "
        f"for m in sys.modules if m.startswith({heavy!r}) and not m.endswith('.base')}}))"
    )
    done = subprocess.run([py, "-c", probe], capture_output=True, text=True, check=True)
    imported = done.stdout.strip().splitlines()[-1]
    print(f"heavy modules imported by --help: {imported}")
    ok = all(
        statistics.median(times[n]) <= 2 * floor
        for n in ("imufdi --help", "imufdi info small.mcap")
    )
    print("target <= 2x: " + ("met" if ok else "NOT met"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
