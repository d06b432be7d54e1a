"""Alarm-episode explanations: fault class and size intervals on fresh seeds, and cost.

Usage::

    python studies/episodes.py --preset paper-table4 --seeds 9600:9620 \
        --detectors glt,pca-parity,bank,noise-glr [--faults 3] [--models step,drift] [--timing]
    python studies/episodes.py --preset paper-table4 --seeds 14000:14002 \
        --detectors noise-glr --far-s 1800     # fault-free episodes per hour

For each seed a log of ``10 + 10 K`` s of the preset is simulated, and for each fault model
K faults are injected one after another on K different IMUs (axis drawn from the seed), the
i-th at ``8 + 10 i + U[0, 1)`` s for 4 s (6 s of recovery before the next):

    step 0.9 deg/s, drift 10 deg/s^2, noise x3, stuck, spikes 5 Hz of 3 deg/s
    (and, with ``--models scale``, a scale factor 1.01: not a reference fault)

``imufdi detect`` (library, all detectors in one pass, 2 s calibration window) writes the
explained episodes; each detector's gyro episodes are matched to the truth
(:func:`imufdi_cli.episodes.match_episodes`) and scored per true model: the faults with at
least one matched episode, the share of matched episodes whose class is right (target
>= 90 %), and the share whose 90 % size interval covers the injected size (target 85-95 %)
with its Clopper-Pearson 95 % interval. Each table row is one detector and fault model.
False episodes per hour come from the fault-free seconds between the end of the
calibration window and the first onset. ``--timing`` also runs detect with
``explain=False`` on the same logs, and report on both outputs, and prints the two time
ratios (report's: the cost of reading and scoring the episodes) with the load average.

The method was developed on seeds 0-7 (docs/episodes.md lists every evaluation set and what
changed after it); evaluation sets must not have been used for any choice.
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

import numpy as np

from imufdi_cli.detect import detect_file
from imufdi_cli.episodes import VARIANCE_DROP, match_episodes
from imufdi_cli.faults import inject_file
from imufdi_cli.mcapio import McapSource, read_events
from imufdi_cli.pipeline import simulate_file
from imufdi_cli.report import build_report, truth_windows

FAULTS = {
    "step": "step:{s},at={at}s,duration=4s,amp=0.9deg/s",
    "drift": "drift:{s},at={at}s,duration=4s,rate=10deg/s^2",
    "noise": "noise:{s},at={at}s,duration=4s,factor=3",
    "stuck": "stuck:{s},at={at}s,duration=4s",
    "spikes": "spikes:{s},at={at}s,duration=4s,rate=5Hz,amp=3deg/s",
    # not in the reference set of fault models (not run unless --models names it): checks that a
    # genuine scale-factor fault is still classed as scale
    "scale": "scale:{s},at={at}s,duration=4s,factor=1.01",
}
DEFAULT_MODELS = "step,drift,noise,stuck,spikes"
CALIBRATION_S = 2.0


def clopper_pearson(k: int, n: int, level: float = 0.95) -> tuple[float, float]:
    """Exact binomial confidence interval of a proportion k / n."""
    from scipy.stats import beta

    tail = (1 - level) / 2
    low = 0.0 if k == 0 else float(beta.ppf(tail, k, n - k + 1))
    high = 1.0 if k == n else float(beta.ppf(1 - tail, k + 1, n - k))
    return low, high


def gyro_axes(path: str) -> list[str]:
    """Gyro sensor ids of a log (e.g. imu3.gyro.x), in array order."""
    from imufdi_cli.mcapio import ImuArrayReader

    return list(ImuArrayReader(path).array.sensor_ids("gyro"))


def merge(states: list[dict[str, Any]]) -> dict[str, Any]:
    """Tallies of several runs (``--dump`` files of disjoint seed ranges) as one."""
    out = dict(states[0])
    for key in ("rows", "detected", "wrong", "false_episodes"):
        out[key] = {}
    out["seeds"], out["fault_free_hours"], out["faults_per_model"] = [], 0.0, 0
    for state in states:
        for key in ("preset", "faults_per_log", "detectors", "models"):
            if state[key] != out[key]:
                raise SystemExit(f"cannot merge runs with different {key}")
        out["seeds"] += state["seeds"]
        out["fault_free_hours"] += state["fault_free_hours"]
        out["faults_per_model"] += state["faults_per_model"]
        for k, v in state["rows"].items():
            out["rows"][k] = out["rows"].get(k, []) + v
        for k, v in state["detected"].items():
            out["detected"][k] = out["detected"].get(k, []) + v
        for key in ("wrong", "false_episodes"):
            for k, v in state[key].items():
                out[key][k] = out[key].get(k, 0) + v
    return out


def print_tables(state: dict[str, Any]) -> None:
    """The Markdown table of docs/episodes.md and the false-episode rates."""
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    seeds = ", ".join(f"{a}-{b - 1}" for a, b in state["seeds"])
    n_faults = state["faults_per_model"]
    print(
        f"{state['preset']} gyro, seeds {seeds}, {state['faults_per_log']} faults per log"
        f" ({n_faults} per model); load average {load}"
    )
    print()
    print(
        "| detector | fault | detected | episodes (wrong sensor) | class right |"
        " 90 % interval covers | coverage 95 % CI | classes found |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for detector in state["detectors"]:
        for model in state["models"]:
            key = f"{detector}|{model}"
            got = state["rows"].get(key, [])
            n = len(got)
            right = sum(bool(r["class_right"]) for r in got)
            sized = [r for r in got if r["covered"] is not None]
            covered = sum(bool(r["covered"]) for r in sized)
            found: dict[str, int] = defaultdict(int)
            for r in got:
                found[str(r["class"])] += 1
            klass = f"{100 * right / n:.1f} %" if n else "-"
            if sized:
                cov = f"{100 * covered / len(sized):.1f} % ({covered}/{len(sized)})"
                c_lo, c_hi = clopper_pearson(covered, len(sized))
                ci = f"{100 * c_lo:.0f}-{100 * c_hi:.0f} %"
            else:
                cov = ci = "-"
            classes = ", ".join(f"{k} {v}" for k, v in sorted(found.items(), key=lambda x: -x[1]))
            print(
                f"| {detector} | {model} | {len(state['detected'].get(key, []))}/{n_faults} |"
                f" {n} ({state['wrong'].get(key, 0)}) | {klass} | {cov} | {ci} | {classes} |"
            )
    print()
    hours = state["fault_free_hours"]
    for detector in state["detectors"]:
        count = state["false_episodes"].get(detector, 0)
        print(
            f"{detector}: false episodes between calibration and first onset:"
            f" {count / hours:.0f} per hour ({count} in {hours * 3600:.0f} s)"
        )


def fault_free(args: argparse.Namespace) -> int:
    """Episodes per hour of each detector (and the variance-drop monitor) on fault-free
    logs of ``--far-s`` seconds, after the calibration window, with the classes found."""
    lo, hi = (int(x) for x in args.seeds.split(":"))
    detectors = args.detectors.split(",")
    counts: dict[str, dict[str, int]] = defaultdict(lambda: defaultdict(int))
    hours = 0.0
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(lo, hi):
            base, out = str(Path(tmp) / "s.mcap"), str(Path(tmp) / "d.mcap")
            simulate_file(args.preset, base, seed=seed, options={"duration": args.far_s})
            detect_file(base, out, [(d, {}) for d in detectors])
            for _, e in read_events(out, "/imufdi/events"):
                if e["event"] != "episode" or e["sensor_type"] != "gyro":
                    continue
                episode = e["episode"]
                counts[episode["detector"]][str(episode["fault_class"])] += 1
            hours += (args.far_s - CALIBRATION_S) / 3600
            print(f"seed {seed} done", file=sys.stderr, flush=True)
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    print(
        f"{args.preset} gyro, fault-free, seeds {lo}-{hi - 1}, {hours * 3600:.0f} s after"
        f" calibration; load average {load}"
    )
    for detector in [*detectors, VARIANCE_DROP]:
        found = counts.get(detector, {})
        total = sum(found.values())
        classes = ", ".join(f"{k} {v}" for k, v in sorted(found.items(), key=lambda x: -x[1]))
        print(f"{detector}: {total} episodes, {total / hours:.1f} per hour ({classes})")
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--preset", default="paper-table4")
    parser.add_argument("--seeds", default="0:8")
    parser.add_argument("--detectors", default="glt")
    parser.add_argument("--faults", type=int, default=3, help="faults per log (K)")
    parser.add_argument("--models", default=DEFAULT_MODELS)
    parser.add_argument("--timing", action="store_true")
    parser.add_argument("--dump", help="write the tallies and every matched episode's fit (JSON)")
    parser.add_argument(
        "--merge", nargs="+", help="print the tables of these --dump files (disjoint seeds)"
    )
    parser.add_argument(
        "--far-s",
        type=float,
        help="instead: false episodes per hour on fault-free logs of this many seconds",
    )
    args = parser.parse_args()
    if args.far_s:
        return fault_free(args)
    if args.merge:
        print_tables(merge([json.loads(Path(p).read_text()) for p in args.merge]))
        return 0
    lo, hi = (int(x) for x in args.seeds.split(":"))
    # the variance-drop monitor's episodes (a detection of the explanation layer, written
    # once per sensor type) are scored like a detector's
    detectors = [*args.detectors.split(","), VARIANCE_DROP]
    models = args.models.split(",")
    K = args.faults
    # (detector, model) -> matched episode records; (detector, model) -> detected fault ids
    rows: dict[tuple[str, str], list[dict[str, Any]]] = defaultdict(list)
    detected: dict[tuple[str, str], set[str]] = defaultdict(set)
    wrong: dict[tuple[str, str], int] = defaultdict(int)
    false_episodes: dict[str, int] = defaultdict(int)
    fault_free_hours = 0.0
    injected = 0
    time_on = time_off = report_on = report_off = 0.0
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        for seed in range(lo, hi):
            base = str(work / f"s{seed}.mcap")
            simulate_file(args.preset, base, seed=seed, options={"duration": 10.0 + 10.0 * K})
            axes = gyro_axes(base)
            imus = sorted({a.split(".")[0] for a in axes})
            rng = np.random.default_rng(seed)
            for model in models:
                chosen = rng.choice(len(imus), size=K, replace=False)
                specs, first_at = [], None
                for i, imu in enumerate(chosen):
                    choices = [a for a in axes if a.split(".")[0] == imus[imu]]
                    sensor = choices[rng.integers(len(choices))]
                    at = 8.0 + 10.0 * i + rng.random()
                    first_at = at if first_at is None else first_at
                    specs.append(FAULTS[model].format(s=sensor, at=f"{at:.3f}"))
                faulty = str(work / "f.mcap")
                inject_file(base, faulty, specs, [], seed=seed)
                injected += K
                out = str(work / "d.mcap")
                pairs: list[tuple[str, dict[str, Any]]] = [
                    (d, {}) for d in detectors if d != VARIANCE_DROP
                ]
                if args.timing:
                    quiet = str(work / "q.mcap")
                    start = time.perf_counter()
                    detect_file(faulty, quiet, pairs, explain=False)
                    time_off += time.perf_counter() - start
                    start = time.perf_counter()
                    build_report(quiet)
                    report_off += time.perf_counter() - start
                start = time.perf_counter()
                detect_file(faulty, out, pairs)
                time_on += time.perf_counter() - start
                if args.timing:
                    start = time.perf_counter()
                    build_report(out)
                    report_on += time.perf_counter() - start
                with McapSource(out) as src:
                    list(src.batches())
                    truth = truth_windows(dict(src.metadata))
                assert truth is not None
                faults = [
                    {**d, "start_ns": w.start_ns, "end_ns": w.end_ns}
                    for w, d in zip(truth.windows, truth.descriptions)
                ]
                onset_ns = min(f["start_ns"] for f in faults)
                assert first_at is not None
                calibrated_ns = onset_ns - round((first_at - CALIBRATION_S) * 1e9)
                events = [
                    e["episode"]
                    for _, e in read_events(out, "/imufdi/events")
                    if e["event"] == "episode" and e["sensor_type"] == "gyro"
                ]
                for detector in detectors:
                    episodes = [e for e in events if e["detector"] == detector]
                    for episode, match in zip(episodes, match_episodes(episodes, faults)):
                        key = (detector, model)
                        if match["match"] == "fault":
                            best = (episode["fits"] or [{}])[0]
                            rows[key].append(
                                {
                                    **match,
                                    "class": episode["fault_class"],
                                    "seed": seed,
                                    "size": best.get("size"),
                                    "low": best.get("low"),
                                    "high": best.get("high"),
                                    "extra": best.get("extra"),
                                    "true_size": match.get("true_size"),
                                    # where the fit sits against the truth (diagnostics)
                                    "start_ns": episode["start_ns"],
                                    "end_ns": episode["end_ns"],
                                    "fragments": episode.get("fragments"),
                                    "onset_index": best.get("onset_index"),
                                    "end_index": best.get("end_index"),
                                    "fault_start_ns": next(
                                        f["start_ns"]
                                        for f in faults
                                        if f["id"] == match["fault_id"]
                                    ),
                                    "fault_end_ns": next(
                                        f["end_ns"] for f in faults if f["id"] == match["fault_id"]
                                    ),
                                }
                            )
                            detected[key].add(f"{seed}:{match['fault_id']}")
                        elif match["match"] == "wrong_sensor":
                            wrong[key] += 1
                        elif episode["start_ns"] >= calibrated_ns and episode["end_ns"] < onset_ns:
                            false_episodes[detector] += 1
                fault_free_hours += (first_at - CALIBRATION_S) / 3600
            print(f"seed {seed} done", file=sys.stderr, flush=True)
    state = {
        "preset": args.preset,
        "seeds": [[lo, hi]],
        "faults_per_log": K,
        "detectors": detectors,
        "models": models,
        "rows": {f"{d}|{m}": got for (d, m), got in rows.items()},
        "detected": {f"{d}|{m}": sorted(ids) for (d, m), ids in detected.items()},
        "wrong": {f"{d}|{m}": n for (d, m), n in wrong.items()},
        "false_episodes": dict(false_episodes),
        "fault_free_hours": fault_free_hours,
        "faults_per_model": injected // max(len(models), 1),
    }
    if args.dump:
        Path(args.dump).write_text(json.dumps(state))
    print_tables(state)
    if args.timing:
        load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
        print(
            f"detect time with explanations / without: {time_on / time_off:.2f}x;"
            f" report time on the explained / unexplained output: {report_on / report_off:.2f}x"
            f" (load average {load})"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
