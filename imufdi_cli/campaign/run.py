"""One campaign run in memory: simulate or read the base, inject, detect, score."""

from __future__ import annotations

import json
import time
import traceback
from collections.abc import Mapping, Sequence
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from imufdi_cli.campaign.spec import DEFAULT_MATCH_FAR, read_base, run_key
from imufdi_cli.errors import ImufdiError
from imufdi_cli.fileio import write_text
from imufdi_cli.metrics import (
    METRIC_NAMES,
    FaultWindow,
)

#: Samples per block streamed through a detector (as `imufdi detect` reads a log).
BLOCK_SAMPLES = 4096
NS_PER_S = 1_000_000_000


def jittered_specs(
    specs: Sequence[str], jitters: Sequence[float | None] | None, seed: int, array: Any
) -> tuple[list[str], list[float | None]]:
    """Fault specs with their onsets drawn per seed; returns the specs applied and each
    fault's onset in seconds from the log start (None for faults without ``at``).

    The draw depends only on the seed and the fault's position in the run, so every
    detector and amplitude of a seed sees the same onset (paired comparisons).
    """
    from imufdi_cli.faults import parse_fault_spec

    out: list[str] = []
    onsets: list[float | None] = []
    for index, spec in enumerate(specs):
        jitter = None if not jitters else jitters[index]
        fault = parse_fault_spec(spec, array)
        onset = fault.at_ns / NS_PER_S
        if jitter:
            rng = np.random.default_rng([int(seed), index, 0x4A17])
            onset += float(rng.uniform(0.0, jitter))
            head, *items = spec.split(",")
            items = [it for it in items if not it.startswith("at=")]
            spec = ",".join([head, *items, f"at={onset:.9f}s"])
        out.append(spec)
        onsets.append(onset)
    return out, onsets


def execute_run(desc: Mapping[str, Any]) -> dict[str, Any]:
    """Run one campaign run in this process; never raises (errors are recorded)."""
    start = time.perf_counter()
    try:
        figures = _execute(desc)
        return {
            "key": run_key(desc),
            "run": dict(desc),
            "ok": True,
            "metrics": figures,
            "seconds": time.perf_counter() - start,
        }
    except Exception as err:  # a failed run is a result, the campaign goes on
        internal = not isinstance(err, ImufdiError)
        message = f"{type(err).__name__}: {err}" if internal else str(err)
        return {
            "key": run_key(desc),
            "run": dict(desc),
            "ok": False,
            "error": message or type(err).__name__,
            "internal": internal,
            "traceback": "" if isinstance(err, ImufdiError) else traceback.format_exc(limit=5),
            "seconds": time.perf_counter() - start,
        }


@lru_cache(maxsize=2)
def _simulated(preset: str, options: str, seed: int) -> tuple[Any, Any]:
    """The simulated base log of a run: ``(ArrayConfig, ImuBlock)``, kept for the next runs
    of the same base and seed (the executors hand out runs grouped by base and seed; every
    run injects into a copy, :meth:`~imufdi_cli.faults.FaultInjector.apply_block`)."""
    from imufdi_cli.simulate import config_from_options, simulate_block

    config = config_from_options(preset, seed=seed, **json.loads(options))
    return simulate_block(config)


def run_order(desc: Mapping[str, Any]) -> tuple[str, int]:
    """Sort key grouping runs by base and seed, so that consecutive runs reuse one
    simulated base log (:func:`_simulated`); the order of execution changes no output."""
    return json.dumps(desc["base"], sort_keys=True), int(desc["seed"])


def write_json_atomic(path: Path, data: Any, *, sweep: bool = True) -> None:
    """``data`` as sorted-key JSON, written atomically (numpy scalars as Python numbers)."""
    write_text(str(path), json.dumps(data, sort_keys=True, default=_jsonable) + "\n", sweep=sweep)


def _jsonable(value: Any) -> Any:
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (np.floating,)):
        return float(value)
    raise TypeError(type(value).__name__)


def store_result(result: Mapping[str, Any], runs_dir: Path) -> dict[str, Any]:
    """Write a run's result to ``runs_dir/<key>.json`` (atomically, without sweeping the
    directory for stale temporary files: the campaign swept it once) and return its status:
    key, ok, seconds and, for a failed run, error and internal."""
    write_json_atomic(runs_dir / f"{result['key']}.json", result, sweep=False)
    return {k: result[k] for k in ("key", "ok", "seconds", "error", "internal") if k in result}


def run_and_store(descs: Sequence[Mapping[str, Any]], runs_dir: str) -> list[dict[str, Any]]:
    """Execute runs one after the other in this process, each result written as soon as it
    is known; returns their statuses (what a pool worker sends back to the campaign)."""
    return [store_result(execute_run(desc), Path(runs_dir)) for desc in descs]


def _execute(desc: Mapping[str, Any]) -> dict[str, Any]:
    """The figures of one run per sensor type: metrics (out-of-sample FAR, delays at
    decision time, MAR at the matched FAR), per-fault events, onsets and faults applied."""
    from imufdi_cli.detect import calibration_window_ns
    from imufdi_cli.detectors import make_detector
    from imufdi_cli.faults import FaultInjector, parse_fault_spec
    from imufdi_cli.log import iter_blocks

    seed = int(desc["seed"])
    array, block = _base_log(desc["base"], seed)
    specs, onsets = jittered_specs(desc["faults"], desc.get("at_jitter"), seed, array)
    faults = [parse_fault_spec(spec, array) for spec in specs]
    t0 = int(block.t_ns[0])
    faulty = FaultInjector(faults, array, seed=seed, t0_ns=t0).apply_block(block)
    detector = make_detector(desc["detector"], desc["params"])
    window = calibration_window_ns(t0, int(faulty.t_ns[-1]), *desc["calibrate"])
    assert window is not None
    keep = (faulty.t_ns >= window[0]) & (faulty.t_ns < window[1])
    detector.fit(faulty.mask(keep), array)
    scorer = _Scorer(array, faults, faulty.t_ns, window, detector)
    for part in iter_blocks(faulty, BLOCK_SAMPLES):
        scorer.passed += len(part)
        scorer.score(detector.process(part))
    scorer.score(detector.flush())
    target = float(desc.get("match_far", DEFAULT_MATCH_FAR))
    figures: dict[str, Any] = {}
    for sensor_type, acc in scorer.accumulators.items():
        metrics = acc.result()
        note = acc.matched(metrics, target)
        figures[sensor_type] = {name: metrics.value(name) for name in METRIC_NAMES} | {
            "faults": [f.to_dict() for f in metrics.faults],
            "onsets_s": onsets,
            "applied_faults": specs,
            "target_far": target,
            "notes": [note] if note else [],
        }
    return figures


def _base_log(base: Mapping[str, Any], seed: int) -> tuple[Any, Any]:
    """``(ArrayConfig, ImuBlock)`` of a run's base: the preset simulated with the run's
    seed, or the file (both cached, never modified)."""
    if "preset" in base:
        return _simulated(base["preset"], json.dumps(base.get("options", {}), sort_keys=True), seed)
    return read_base(base["file"])


class _Scorer:
    """Feeds a detector's outputs to one MetricsAccumulator per sensor type, each row
    stamped with its decision time (as :mod:`imufdi_cli.detect` writes it)."""

    def __init__(
        self, array: Any, faults: Sequence[Any], t_ns: np.ndarray, window: Any, detector: Any
    ) -> None:
        from imufdi_cli.detect import lookahead_of

        self.array = array
        self.faults = faults
        self.t_ns = t_ns
        self.t0 = int(t_ns[0])
        self.window = (window[0], window[1])
        self.lookahead = lookahead_of(detector)
        self.accumulators: dict[str, Any] = {}
        self.emitted: dict[str, int] = {}
        self.passed = 0  # samples given to the detector so far

    def _accumulator(self, sensor_type: str) -> Any:
        from imufdi_cli.metrics import MetricsAccumulator

        if sensor_type not in self.accumulators:
            ids = self.array.sensor_ids(sensor_type)
            windows = []
            for fault in self.faults:
                if fault.sensor_type != sensor_type:
                    continue
                columns = [ids.index(s) for s in fault.sensors if s in ids]
                end = None if fault.until_ns is None else self.t0 + fault.until_ns
                windows.append(FaultWindow(fault.id, tuple(columns), self.t0 + fault.at_ns, end))
            self.accumulators[sensor_type] = MetricsAccumulator(
                len(ids), windows, calibration_ns=self.window
            )
            self.emitted[sensor_type] = 0
        return self.accumulators[sensor_type]

    def score(self, outputs: Mapping[str, Any]) -> None:
        from imufdi_cli.detect import decision_positions

        for sensor_type, out in outputs.items():
            accumulator = self._accumulator(sensor_type)
            rows = len(out)
            first = self.emitted[sensor_type]
            positions = decision_positions(first, rows, self.passed, self.lookahead)
            accumulator.update(
                self.t_ns[first : first + rows],
                out.alarm,
                out.isolated,
                decided_ns=self.t_ns[positions],
                isolated_set=out.isolated_set,
                statistic=out.statistic,
                threshold=out.threshold,
                scores=out.scores,
            )
            self.emitted[sensor_type] = first + rows
