"""woa-mvmd-glt speed as a multiple of real time, against GLT on the same log, same run.

Usage: python benchmarks/bench_woa.py [--duration 20] [--seed 7000]

A paper-table4 log (16 IMUs, 100 Hz, gyro + accel) is simulated once; each detector is fitted
on 0-2 s and streams the whole log in blocks of 64 samples (as ``imufdi detect`` does). The
figure is log duration / wall time ("x real time"): woa-mvmd-glt with its defaults (WOA tuning
of both sensor types included), woa-mvmd-glt with (K, alpha) given (no tuning: the windowed
MVMD alone), and GLT as the peer measured in the same run.

Target (issue "Fast where users wait"): woa-mvmd-glt >= 50x real time on paper-table4 with
unchanged detection figures.
"""

from __future__ import annotations

import argparse
import os
import time

from imufdi_cli.detectors import make_detector
from imufdi_cli.log import iter_blocks
from imufdi_cli.simulate import preset, simulate_block


def realtime(name: str, params: dict[str, object], block, array, seconds: float) -> float:
    start = time.perf_counter()
    det = make_detector(name, params)
    det.fit(block.slice(0, int(2.0 * array.rate_hz)), array)
    for part in iter_blocks(block, 64):
        det.process(part)
    det.flush()
    return seconds / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--duration", type=float, default=20.0, help="log length, s")
    parser.add_argument("--seed", type=int, default=7000)
    args = parser.parse_args()
    array, block = simulate_block(preset("paper-table4", seed=args.seed, duration=args.duration))
    seconds = len(block) / array.rate_hz
    print(f"paper-table4, {seconds:g} s, 16 IMUs, 100 Hz; load average {os.getloadavg()}")
    runs = {
        "glt (peer)": ("glt", {}),
        "woa-mvmd-glt, defaults (tuning included)": ("woa-mvmd-glt", {}),
        "woa-mvmd-glt, K=2 mvmd_alpha=550 (no tuning)": (
            "woa-mvmd-glt",
            {"K": 2, "mvmd_alpha": 550.0},
        ),
    }
    for name, params in runs.values():  # import modules (and scipy) outside the timing
        make_detector(name, params)
    ratios = {label: realtime(n, p, block, array, seconds) for label, (n, p) in runs.items()}
    glt = ratios["glt (peer)"]
    for label, ratio in ratios.items():
        print(f"  {label:46s} {ratio:9.1f}x real time  ({glt / ratio:7.1f}x slower than glt)")
    woa = ratios["woa-mvmd-glt, defaults (tuning included)"]
    print(f"  target >= 50x real time: {'met' if woa >= 50 else 'NOT met'} ({woa:.1f}x)")
    print(f"load average after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
