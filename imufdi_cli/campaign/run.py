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
from imufdi_cli.metrics import METRIC_NAMES

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
    """The figures of one run per sensor type, as ``inject | detect | report`` computes
    them: the run's faults applied in memory, the detection core
    (:class:`~imufdi_cli.engine.Engine`: conditioning, calibration window, decision times)
    and the report's scoring (:class:`~imufdi_cli.report.channel.ChannelScore`); plus
    per-fault events, onsets, the faults applied and each type's budget curve (the matched
    budget is pooled over runs by the summary)."""
    from imufdi_cli.detectors import make_detector
    from imufdi_cli.engine import Engine, with_budget
    from imufdi_cli.faults import FaultInjector, parse_fault_spec
    from imufdi_cli.log import iter_blocks
    from imufdi_cli.report.truth import truth_of_runs
    from imufdi_cli.validity import Conditioner

    seed = int(desc["seed"])
    array, block = _base_log(desc["base"], seed)
    specs, onsets = jittered_specs(desc["faults"], desc.get("at_jitter"), seed, array)
    faults = [parse_fault_spec(spec, array) for spec in specs]
    t0 = int(block.t_ns[0])
    injector = FaultInjector(faults, array, seed=seed, t0_ns=t0)
    faulty = injector.apply_block(block)
    ((name, params),) = with_budget([(desc["detector"], desc["params"])], desc.get("false_alarms"))
    detector = make_detector(name, params)
    truth = truth_of_runs([{"t0_ns": t0, "faults": [f.to_dict() for f in injector.faults]}])
    conditioner = Conditioner(array)
    sink = ScoringSink(array, truth, conditioner)
    calibrate = desc["calibrate"]
    # the run's log is in memory and never modified: the engine holds views of it
    engine = Engine(
        [detector], array, conditioner, sink, calibrate=(calibrate[0], calibrate[1]), copy=False
    )
    sink.engine = engine
    for part in iter_blocks(faulty, BLOCK_SAMPLES):
        engine.add_block(part)
    engine.finish()
    target = float(desc.get("match_far", DEFAULT_MATCH_FAR))
    figures: dict[str, Any] = {}
    # the reference delays read the budget from the detector's metadata (none without one)
    under_budget = float(getattr(detector, "false_alarms", 0.0) or 0.0) > 0
    record_metadata = detector.metadata() if under_budget else {}
    for sensor_type, score in sink.scores.items():
        assert score.record is not None
        score.record["detector_metadata"] = record_metadata
        metrics, notes = score.metrics(match_far=target)
        curve = score.accumulator.budget_curve()
        figures[sensor_type] = (
            metrics.to_dict() | {name: metrics.value(name) for name in METRIC_NAMES}
        ) | {
            "validity": dict(score.validity),
            "onsets_s": onsets,
            "applied_faults": specs,
            "target_far": target,
            "notes": notes,
            "budget_curve": None if curve is None else curve.to_dict(),
        }
    return figures


class ScoringSink:
    """The detection core's sink of a campaign run: each sensor type's rows scored in
    memory by the report's :class:`~imufdi_cli.report.channel.ChannelScore` (rows
    excluded as clipped or invalid by the conditioner's record of them so far, as the
    report excludes them from the record ``detect`` writes)."""

    def __init__(self, array: Any, truth: Any, conditioner: Any) -> None:
        self.array = array
        self.truth = truth
        self.conditioner = conditioner
        self.engine: Any = None  # set once the engine exists
        self.scores: dict[str, Any] = {}

    def rows(
        self, track: Any, sensor_type: str, t_ns: np.ndarray, decided_ns: np.ndarray, out: Any
    ) -> None:
        from imufdi_cli.report.channel import ChannelScore, rows_of_block

        score = self.scores.get(sensor_type)
        if score is None:
            window = self.engine.calibration_window()
            score = self.scores[sensor_type] = ChannelScore(
                track.name,
                sensor_type,
                self.array.sensor_ids(sensor_type),
                truth=self.truth,
                calibration_ns=None if window is None else (window[0], window[1]),
                record={"t0_ns": self.engine.t_first},
                rate_hz=self.array.rate_hz,
            )
        record = score.record
        assert record is not None
        record["validity"] = self.conditioner.metadata()
        score.add(rows_of_block(t_ns, decided_ns, out))

    def episodes(self, track: Any, episodes: Any) -> None:
        """Campaign runs explain no episodes."""


def _base_log(base: Mapping[str, Any], seed: int) -> tuple[Any, Any]:
    """``(ArrayConfig, ImuBlock)`` of a run's base: the preset simulated with the run's
    seed, or the file (both cached, never modified)."""
    if "preset" in base:
        return _simulated(base["preset"], json.dumps(base.get("options", {}), sort_keys=True), seed)
    return read_base(base["file"])
