"""woa-mvmd-glt speed as a multiple of real time, against GLT on the same log, same run.

Usage: python benchmarks/bench_woa.py [--duration 20] [--seed 7000] [--repeat 3]

A paper-table4 log (16 IMUs, 100 Hz, gyro + accel) is simulated once; each detector is fitted
on 0-2 s and streams the whole log in blocks (4096 samples, as ``imufdi detect`` reads an
MCAP file and ``imufdi campaign`` feeds its runs; and 64 samples, a live capture's small
blocks). The figure is log duration / time ("x real time", median of ``--repeat`` runs), by
wall time and by the process's CPU time (on the shared 2-core build machine the wall time
mostly measures the other jobs; the CPU time is the work itself): woa-mvmd-glt with its defaults (WOA tuning of both sensor types included, a cost
paid once per fit; the tuning cache is cleared before every run), with (K, alpha) given (no tuning: the windowed MVMD alone), the WOA
tuning alone, and GLT as the peer measured in the same run. The load average is printed
before and after.

Target (docs/performance.md): woa-mvmd-glt >= 50x real time on paper-table4 with
unchanged detection figures.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

from imufdi_cli.detectors import make_detector
from imufdi_cli.detectors.woa_mvmd_glt import clear_tuning_cache
from imufdi_cli.log import iter_blocks
from imufdi_cli.simulate import preset, simulate_block


def seconds(
    name: str, params: dict[str, object], block, array, block_size: int
) -> tuple[float, float]:
    """Wall and CPU time of fit (0-2 s) + streaming the whole log + flush."""
    clear_tuning_cache()  # every run tunes afresh
    start, cpu = time.perf_counter(), time.process_time()
    det = make_detector(name, params)
    det.fit(block.slice(0, int(2.0 * array.rate_hz)), array)
    for part in iter_blocks(block, block_size):
        det.process(part)
    det.flush()
    return time.perf_counter() - start, time.process_time() - cpu


def fit_seconds(name: str, params: dict[str, object], block, array) -> tuple[float, float]:
    clear_tuning_cache()
    start, cpu = time.perf_counter(), time.process_time()
    make_detector(name, params).fit(block.slice(0, int(2.0 * array.rate_hz)), array)
    return time.perf_counter() - start, time.process_time() - cpu


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--duration", type=float, default=20.0, help="log length, s")
    parser.add_argument("--seed", type=int, default=7000)
    parser.add_argument("--repeat", type=int, default=3, help="runs per figure (median)")
    args = parser.parse_args()
    array, block = simulate_block(preset("paper-table4", seed=args.seed, duration=args.duration))
    log_s = len(block) / array.rate_hz
    print(f"paper-table4, {log_s:g} s, 16 IMUs, 100 Hz; load average {os.getloadavg()}")
    fixed = {"K": 2, "mvmd_alpha": 550.0}
    runs = {
        "glt (peer), blocks of 4096": ("glt", {}, 4096),
        "woa-mvmd-glt defaults (tuning incl.), 4096": ("woa-mvmd-glt", {}, 4096),
        "woa-mvmd-glt K=2 mvmd_alpha=550, 4096": ("woa-mvmd-glt", fixed, 4096),
        "woa-mvmd-glt K=2 mvmd_alpha=550, 64": ("woa-mvmd-glt", fixed, 64),
    }
    for name, params, _ in runs.values():  # import modules (and scipy) outside the timing
        make_detector(name, params)
    ratios, cpu_ratios = {}, {}
    for label, (name, params, size) in runs.items():
        times = [seconds(name, params, block, array, size) for _ in range(args.repeat)]
        ratios[label] = log_s / statistics.median(t[0] for t in times)
        cpu_ratios[label] = log_s / statistics.median(t[1] for t in times)
    fits = [fit_seconds("woa-mvmd-glt", {}, block, array) for _ in range(args.repeat)]
    glt, glt_cpu = ratios["glt (peer), blocks of 4096"], cpu_ratios["glt (peer), blocks of 4096"]
    print(f"  {'':44s} {'wall':>8s}  {'vs glt':>7s}  {'CPU time':>9s}  {'vs glt':>7s}")
    for label, ratio in ratios.items():
        cpu = cpu_ratios[label]
        print(
            f"  {label:44s} {ratio:7.1f}x  {glt / ratio:6.1f}x  {cpu:8.1f}x  {glt_cpu / cpu:6.1f}x"
        )
    print(
        f"  (x real time = log duration / time; 'vs glt' = times slower than glt)\n"
        f"  WOA tuning of gyro + accel (fit with defaults): wall"
        f" {statistics.median(f[0] for f in fits):.2f} s, CPU {statistics.median(f[1] for f in fits):.2f} s"
    )
    for label in (
        "woa-mvmd-glt defaults (tuning incl.), 4096",
        "woa-mvmd-glt K=2 mvmd_alpha=550, 4096",
    ):
        wall, cpu = ratios[label], cpu_ratios[label]
        print(
            f"  target >= 50x real time, {label}: wall {'met' if wall >= 50 else 'NOT met'}"
            f" ({wall:.1f}x), CPU time {'met' if cpu >= 50 else 'NOT met'} ({cpu:.1f}x)"
        )
    print(f"load average after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
