"""One campaign run through the detection core and the report's scoring, against the way
runs were made before (the baseline), CPU seconds, in one process.

The work is docs/campaigns/compare.toml (its first ``--seeds`` seeds, ``--skip`` leaves
detectors out; cnn-map and woa-mvmd-glt are left out by default: their detectors alone
take 10-40 s a run). Each run is executed both ways, alternately (ABBA within a round, a
warm-up pass first), so that the machine's load hits both alike:

- **baseline**: the base log injected in memory, the detector fitted on the raw
  calibration window and fed 4096-sample blocks, each sensor type's rows scored by a
  ``MetricsAccumulator`` (decision times, matched FAR) -- no conditioning (clipped and
  invalid samples), no false alarm episodes, no budget curve: what a campaign run did
  before it shared ``imufdi detect``'s core;
- **core**: :func:`imufdi_cli.campaign.run.execute_run`, i.e. the engine (conditioning,
  calibration window, decision times) and :class:`~imufdi_cli.report.channel.ChannelScore`
  (exclusions, false alarm episodes at the detector's threshold and at the 71 levels of
  the matched budget, reference delays).

It prints the CPU seconds of both, per detector and in total, their ratio core/baseline
(the cost of one engine: what the conditioner and the budget figures add to a run), and
the load average. Run::

    python benchmarks/bench_campaign_run.py [--seeds 1] [--rounds 3] [--skip cnn-map | --all]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_campaign import subset_spec


def baseline_run(desc: dict[str, Any]) -> dict[str, Any]:
    """A run the previous way (module docstring): the figures per sensor type."""
    from imufdi_cli.campaign.run import _base_log, jittered_specs
    from imufdi_cli.detectors import make_detector
    from imufdi_cli.engine import calibration_window_ns, decision_positions, lookahead_of
    from imufdi_cli.faults import FaultInjector, parse_fault_spec
    from imufdi_cli.log import iter_blocks
    from imufdi_cli.metrics import FaultWindow, MetricsAccumulator

    seed = int(desc["seed"])
    array, block = _base_log(desc["base"], seed)
    specs, _ = jittered_specs(desc["faults"], desc.get("at_jitter"), seed, array)
    faults = [parse_fault_spec(spec, array) for spec in specs]
    t0 = int(block.t_ns[0])
    faulty = FaultInjector(faults, array, seed=seed, t0_ns=t0).apply_block(block)
    detector = make_detector(desc["detector"], desc["params"])
    window = calibration_window_ns(t0, int(faulty.t_ns[-1]), *desc["calibrate"])
    assert window is not None
    keep = (faulty.t_ns >= window[0]) & (faulty.t_ns < window[1])
    detector.fit(faulty.mask(keep), array)
    lookahead = lookahead_of(detector)
    accumulators: dict[str, MetricsAccumulator] = {}
    emitted: dict[str, int] = {}
    passed = 0

    def score(outputs: Any) -> None:
        for sensor_type, out in outputs.items():
            if sensor_type not in accumulators:
                ids = array.sensor_ids(sensor_type)
                windows = [
                    FaultWindow(
                        f.id,
                        tuple(ids.index(s) for s in f.sensors if s in ids),
                        t0 + f.at_ns,
                        None if f.until_ns is None else t0 + f.until_ns,
                    )
                    for f in faults
                    if f.sensor_type == sensor_type
                ]
                accumulators[sensor_type] = MetricsAccumulator(
                    len(ids), windows, calibration_ns=(window[0], window[1])
                )
                emitted[sensor_type] = 0
            first = emitted[sensor_type]
            positions = decision_positions(first, len(out), passed, lookahead)
            accumulators[sensor_type].update(
                faulty.t_ns[first : first + len(out)],
                out.alarm,
                out.isolated,
                decided_ns=faulty.t_ns[positions],
                isolated_set=out.isolated_set,
                statistic=out.statistic,
                threshold=out.threshold,
                scores=out.scores,
            )
            emitted[sensor_type] = first + len(out)

    for part in iter_blocks(faulty, 4096):
        passed += len(part)
        score(detector.process(part))
    score(detector.flush())
    figures = {}
    for sensor_type, acc in accumulators.items():
        metrics = acc.result()
        acc.matched(metrics, float(desc.get("match_far", 0.01)))
        figures[sensor_type] = metrics.to_dict()
    return figures


def cpu() -> float:
    return time.process_time()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=1, help="first N seeds of compare.toml")
    parser.add_argument("--rounds", type=int, default=3, help="ABBA rounds over every run")
    parser.add_argument(
        "--skip",
        action="append",
        default=None,
        help="leave a detector out (default: cnn-map and woa-mvmd-glt)",
    )
    parser.add_argument("--all", action="store_true", help="every detector of the spec")
    args = parser.parse_args()
    skip = [] if args.all else ["cnn-map", "woa-mvmd-glt"] if args.skip is None else args.skip
    from imufdi_cli.campaign import execute_run, load_spec

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "compare.toml"
        path.write_text(subset_spec(args.seeds, skip))
        runs = load_spec(path).runs
    load_before = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    for desc in runs:  # warm-up: imports, caches of the simulated bases
        baseline_run(desc)
        execute_run(desc)
    spent: dict[str, dict[str, float]] = defaultdict(lambda: {"baseline": 0.0, "core": 0.0})
    for round_ in range(args.rounds):
        order = ("baseline", "core") if round_ % 2 == 0 else ("core", "baseline")
        for desc in runs:
            for way in order:
                start = cpu()
                if way == "core":
                    result = execute_run(desc)
                    assert result["ok"], result.get("error")
                else:
                    baseline_run(desc)
                spent[desc["detector"] + " " + json.dumps(desc["params"])][way] += cpu() - start
    print(
        f"compare.toml, first {args.seeds} seed(s), "
        + (f"without {', '.join(skip)}" if skip else "every detector")
        + ":"
        f" {len(runs)} runs x {args.rounds} rounds; load average before {load_before}"
    )
    total = {"baseline": 0.0, "core": 0.0}
    for name, ways in sorted(spent.items()):
        for way in total:
            total[way] += ways[way]
        print(
            f"  {name:40s} baseline {ways['baseline']:7.2f} s  core {ways['core']:7.2f} s"
            f"  core/baseline {ways['core'] / ways['baseline']:.3f}"
        )
    ratio = total["core"] / total["baseline"]
    print(
        f"total: baseline {total['baseline']:.2f} s, core {total['core']:.2f} s CPU;"
        f" core/baseline {ratio:.3f}; load average after"
        f" {', '.join(f'{x:.1f}' for x in os.getloadavg())}"
    )


if __name__ == "__main__":
    main()
