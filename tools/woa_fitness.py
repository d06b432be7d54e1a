"""The WOA fitness on paper-table4: what (K, alpha) it chooses as the alpha bound moves, and
the fitness along alpha for fixed K.

For each seed, the detector's tuning (population 8, 6 iterations, K in [2, 5], alpha from 50
to the bound) runs on the gyro samples of the calibration window (0-2 s of a paper-table4
log) with the chosen fitness, for alpha bounds 5000, 2e4 and 1e6.

Run: PYTHONPATH=$PWD python tools/woa_fitness.py --seeds 100:105 [--fitness cfv|cfv+delay]
"""

from __future__ import annotations

import argparse

import numpy as np

from imufdi_cli.detectors import make_detector
from imufdi_cli.simulate import preset, simulate_block


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", default="100:105", help="START:STOP")
    parser.add_argument("--fitness", default="cfv+delay")
    parser.add_argument("--bounds", default="5000,20000,1000000")
    args = parser.parse_args()
    lo, hi = (int(v) for v in args.seeds.split(":"))
    bounds = [float(b) for b in args.bounds.split(",")]
    print(f"fitness {args.fitness}; chosen (K, alpha) per seed and alpha upper bound")
    print("| seed | " + " | ".join(f"bound {b:g}" for b in bounds) + " |")
    print("|---|" + "---|" * len(bounds))
    for seed in range(lo, hi):
        array, block = simulate_block(preset("paper-table4", seed=seed, duration="3s"))
        cells = []
        for bound in bounds:
            det = make_detector(
                "woa-mvmd-glt",
                {"types": "gyro", "alpha_max": bound, "fitness": args.fitness},
            )
            det.fit(block.slice(0, 200), array)
            meta = det.metadata()["types"]["gyro"]
            cells.append(f"K={meta['K']}, alpha={meta['mvmd_alpha']:.4g}")
        print(f"| {seed} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    np.set_printoptions(precision=4)
    main()
