"""woa-mvmd-glt's WOA tuning on ``imufdi demo``'s input, against another checkout, same run.

Usage: python benchmarks/bench_woa_tune.py --before TREE [--repeat 5] [--demo]

``imufdi demo`` (the README's first command) spends most of its time in woa-mvmd-glt's fit:
the WOA search of (K, alpha) for gyro and accel on the 2 s calibration window. The input is
made at run time as the demo makes it (the bundled ``imufdi_cli/sample_logs/paper-table4.mcap`` with
the demo's step fault injected, seed 1); the calibration window is its first 2 s (200 samples; `imufdi detect`'s conditioning keeps
199 of them, a cost difference of 0.5 %).

Each checkout (this one and ``--before``, e.g. a worktree of main) is timed in its own
interpreter (``PYTHONPATH`` = the checkout, one BLAS thread, as the CLI), the two
interleaved ``--repeat`` times so that a change of machine load hits both alike; per
interpreter, one untimed fit first (first use of scipy's ufuncs, FFT plans), then:

- ``fit``: ``make_detector("woa-mvmd-glt", {}).fit(calibration)`` with the tuning cache
  cleared: what every ``imufdi detect -d woa-mvmd-glt`` without tuned parameters pays;
- ``tune``: ``tune_signal`` of each sensor type in turn (what ``imufdi tune`` pays per type).

Printed: median CPU and wall time per checkout, the ratio this/before (the claim: CPU, the
wall clock of the shared machine mostly measures the other jobs), the load average before
and after, and whether both checkouts chose the same (K, alpha, fitness, curve) (they must).
``--demo`` also times the whole ``python -m imufdi_cli demo -q`` (child CPU and wall),
interleaved the same way.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

WORKER = r"""
import json, sys, time
import numpy as np
from imufdi_cli.detectors import make_detector
from imufdi_cli.detectors.woa_mvmd_glt import clear_tuning_cache, make_validation, tune_signal
from imufdi_cli.mcapio import read_array

array, block = read_array(sys.argv[1])
calibration = block.slice(0, int(np.searchsorted(block.t_ns, block.t_ns[0] + 2_000_000_000)))


def fit():
    clear_tuning_cache()
    det = make_detector("woa-mvmd-glt", {})
    det.fit(calibration, array)
    return det


def tune():
    p = make_detector("woa-mvmd-glt", {}).params
    out = []
    for sensor_type in ("gyro", "accel"):
        values = array.select(calibration.get(sensor_type), sensor_type)
        validation = make_validation(
            values.shape[1],
            int(p["window"]),
            int(p["window"]) - int(p["overlap"]),
            float(p["validation_step"]),
            float(p["delay_weight"]),
            float(p["alpha"]),
        )
        out.append(
            tune_signal(
                np.ascontiguousarray(values[: int(p["tune_samples"])]).T,
                validation=validation,
                population=int(p["population"]),
                iterations=int(p["iterations"]),
                k_bounds=(int(p["k_min"]), int(p["k_max"])),
                rule=str(p["u_best"]),
            )
        )
    return out


def timed(function):
    cpu, wall = time.process_time(), time.perf_counter()
    value = function()
    return time.process_time() - cpu, time.perf_counter() - wall, value


det = fit()  # untimed: first use of the compiled functions and FFT plans
fit_cpu, fit_wall, det = timed(fit)
tune_cpu, tune_wall, tuned = timed(tune)
chosen = {
    t: {k: det.metadata()["types"][t]["tuning"][k] for k in ("K", "alpha", "fitness", "curve")}
    for t in ("gyro", "accel")
}
chosen["tune"] = [[r.K, r.alpha, r.fitness, r.curve] for r in tuned]
print(json.dumps({"fit": [fit_cpu, fit_wall], "tune": [tune_cpu, tune_wall], "chosen": chosen}))
"""


def _environment(tree: Path) -> dict[str, str]:
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "PYTHONPATH": str(tree)}
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    return env


def _worker(tree: Path, log: Path) -> dict:
    done = subprocess.run(
        [sys.executable, "-c", WORKER, str(log)],
        check=True,
        capture_output=True,
        text=True,
        env=_environment(tree),
        cwd=tree,
    )
    return json.loads(done.stdout.strip().splitlines()[-1])


def _demo(tree: Path) -> tuple[float, float]:
    """(CPU, wall) seconds of one ``imufdi demo -q`` in ``tree``."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    subprocess.run(
        [sys.executable, "-m", "imufdi_cli", "demo", "-q"],
        check=True,
        stdout=subprocess.DEVNULL,
        env=_environment(tree),
        cwd=tree,
    )
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime), wall


def _make_input(directory: Path) -> Path:
    """The demo's faulty log (``imufdi_cli.cli.demo.run_demo``'s inject step)."""
    sys.path.insert(0, str(ROOT))
    from imufdi_cli.cli.demo import DEMO_FAULT
    from imufdi_cli.faults.inject import inject_file
    from imufdi_cli.pipeline import SAMPLE_LOGS

    faulty = directory / "faulty.mcap"
    inject_file(str(SAMPLE_LOGS / "paper-table4.mcap"), str(faulty), [DEMO_FAULT], [], seed=1)
    return faulty


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--before", type=Path, required=True, help="checkout to compare with")
    parser.add_argument("--repeat", type=int, default=5, help="interpreters per checkout")
    parser.add_argument("--demo", action="store_true", help="also time `imufdi demo -q`")
    args = parser.parse_args()
    trees = {"this": ROOT, "before": args.before.resolve()}
    load_start = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        log = _make_input(Path(tmp))
        runs: dict[str, list[dict]] = {name: [] for name in trees}
        demos: dict[str, list[tuple[float, float]]] = {name: [] for name in trees}
        for i in range(args.repeat):
            order = list(trees) if i % 2 == 0 else list(reversed(trees))
            for name in order:
                runs[name].append(_worker(trees[name], log))
            if args.demo:
                for name in order:
                    demos[name].append(_demo(trees[name]))
    load_end = os.getloadavg()
    print(
        f"woa-mvmd-glt tuning on the demo's input (paper-table4 sample, 2 s calibration,"
        f" gyro + accel), median of {args.repeat} interpreters per checkout;"
        f" load average {load_start[0]:.2f} -> {load_end[0]:.2f}"
    )
    print(f"  this: {trees['this']}\n  before: {trees['before']}")
    print(f"  {'':34s} {'before':>9s} {'this':>9s} {'this/before':>12s}")
    rows = [("fit (tunes both types)", "fit"), ("tune_signal, gyro then accel", "tune")]
    for label, key in rows:
        for column, unit in ((0, "CPU"), (1, "wall")):
            was = statistics.median(r[key][column] for r in runs["before"])
            now = statistics.median(r[key][column] for r in runs["this"])
            print(f"  {label + ', ' + unit:34s} {was:8.3f}s {now:8.3f}s {now / was:12.2f}")
    if args.demo:
        for column, unit in ((0, "CPU"), (1, "wall")):
            was = statistics.median(d[column] for d in demos["before"])
            now = statistics.median(d[column] for d in demos["this"])
            print(f"  {'imufdi demo -q, ' + unit:34s} {was:8.3f}s {now:8.3f}s {now / was:12.2f}")
    chosen = {json.dumps(r["chosen"], sort_keys=True) for rs in runs.values() for r in rs}
    print(f"  same (K, alpha, fitness, curve) in every run of both checkouts: {len(chosen) == 1}")


if __name__ == "__main__":
    main()
