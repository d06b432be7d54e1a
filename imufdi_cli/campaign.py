"""Fault-injection campaigns: inject + detect + report over a run matrix, in parallel.

A campaign spec (TOML) names base logs (simulate presets with seeds, or files/globs), the
fault matrix, the detectors with parameter grids and the metrics to aggregate. It expands
to a list of small, JSON-able run descriptions; each run is keyed by the SHA-256 of its
canonical description, executed in a worker (process pool or dask.distributed), and its
result written to ``runs/<key>.json`` as soon as it finishes (atomically), so ``--resume``
skips what is done and an interrupted campaign loses at most the runs in flight. A run
that fails is recorded with its error and the campaign goes on.

Runs use the library in memory (simulate or read the base log once, inject with
:class:`~imufdi_cli.faults.FaultInjector`, stream blocks through the detector, score with
:class:`~imufdi_cli.metrics.MetricsAccumulator`, rows stamped with their decision time as
:mod:`imufdi_cli.detect` does): the same maths as ``inject | detect | report
--match-far``, without writing intermediate MCAP files.

Spec example::

    [campaign]
    name = "compare"
    seeds = [0, 1, 2, 3, 4]
    calibrate = "0s:2s"
    match_far = "1%"
    metrics = ["far", "mar", "fir", "detection_delay_s", "mar_at_far"]

    [[base]]
    preset = "paper-table4"

    [[fault]]
    model = "step"
    sensor = ["imu0.gyro.x", "imu7.gyro.z"]
    at = "2.5s"
    at_jitter = "0.5s"
    amp = ["0.3deg/s", "0.6deg/s", "0.9deg/s"]

    [[detector]]
    name = "glt"
    params = { alpha = [0.01, 0.001] }
"""

from __future__ import annotations

import csv
import glob
import hashlib
import io
import itertools
import json
import os
import sys
import threading
import time
import traceback
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from imufdi_cli.errors import CampaignFailedError, CampaignSpecError, ImufdiError, UsageError
from imufdi_cli.fileio import atomic_path, check_outputs, write_text
from imufdi_cli.metrics import (
    METRIC_NAMES,
    FaultWindow,
    mean_metrics,
)

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

DEFAULT_METRICS = [
    "far",
    "mar",
    "accuracy",
    "fir",
    "detection_delay_s",
    "isolation_delay_s",
    "detection_probability",
    "mar_at_far",
]
#: Target FAR of the ``*_at_far`` figures unless ``campaign.match_far`` says otherwise.
DEFAULT_MATCH_FAR = 0.01
BLOCK_SAMPLES = 4096
NS_PER_S = 1_000_000_000
#: BLAS/OpenMP thread caps for worker processes: on a small machine, one BLAS thread per
#: worker process; several threads per worker only fight over the same cores.
WORKER_THREAD_ENV: dict[str, str] = {
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
}


# --- spec ------------------------------------------------------------------------------


@dataclass
class CampaignSpec:
    """A parsed, validated campaign spec."""

    name: str
    runs: list[dict[str, Any]]
    metrics: list[str]
    source: str


def _as_list(value: Any) -> list[Any]:
    return list(value) if isinstance(value, (list, tuple)) else [value]


def _grid(params: Mapping[str, Any]) -> list[dict[str, Any]]:
    """Cartesian product of list-valued entries (scalars are fixed)."""
    keys = sorted(params)
    values = [_as_list(params[k]) for k in keys]
    return [dict(zip(keys, combo)) for combo in itertools.product(*values)]


def _fault_specs(table: Mapping[str, Any], where: str) -> list[str]:
    """Expand one [[fault]] table into spec strings of the CLI grammar (``at_jitter`` is
    not part of the spec: see :func:`_jitter_of`)."""
    if "model" not in table or "sensor" not in table:
        raise CampaignSpecError(f"{where}: needs model and sensor")
    table = {k: v for k, v in table.items() if k != "at_jitter"}
    specs = []
    for combo in _grid(table):
        model = combo.pop("model")
        sensor = combo.pop("sensor")
        items = ",".join(f"{k}={v}" for k, v in sorted(combo.items()))
        specs.append(f"{model}:{sensor}" + (f",{items}" if items else ""))
    return specs


def _jitter_of(table: Mapping[str, Any], where: str) -> float | None:
    """``at_jitter = "0.5s"`` of a [[fault]] table in seconds (None when absent).

    Each run draws its onset uniformly in ``[at, at + at_jitter]`` from its seed
    (:func:`jittered_specs`), so onsets do not sit on one sample or window grid."""
    if "at_jitter" not in table:
        return None
    from imufdi_cli.units import parse_quantity

    if "at" not in table:
        raise CampaignSpecError(f"{where}.at_jitter: needs an onset `at` to jitter")
    try:
        value = parse_quantity(str(table["at_jitter"]), "time", name=f"{where}.at_jitter")
    except ImufdiError as err:
        raise CampaignSpecError(str(err)) from err
    if not value >= 0.0 or not np.isfinite(value):
        raise CampaignSpecError(f"{where}.at_jitter: must be a time >= 0, got {value!r}")
    return float(value)


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


def _calibration_window(value: Any, where: str) -> list[float | None]:
    """``"START:END"`` (times from the log start) -> ``[start_s, end_s or None]``."""
    from imufdi_cli.units import parse_time_range

    try:
        start, end = parse_time_range(str(value), name=where)
    except ImufdiError as err:
        raise CampaignSpecError(str(err)) from err
    return [start, end]


def load_spec(path: str | Path) -> CampaignSpec:
    """Parse and validate a campaign spec; every problem is reported before any run."""
    from imufdi_cli.array import ArrayConfig
    from imufdi_cli.detectors import DETECTORS, make_detector
    from imufdi_cli.faults import parse_fault_spec, validate_faults
    from imufdi_cli.simulate import PRESETS, config_from_options

    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as err:
        raise CampaignSpecError(f"cannot read campaign spec {path}: {err.strerror}") from err
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as err:
        raise CampaignSpecError(f"{path}: not valid TOML ({err})") from err
    except RecursionError as err:  # tomllib parses nested arrays/tables recursively
        raise CampaignSpecError(
            f"{path}: not valid TOML (arrays or tables nested too deeply)"
        ) from err
    known = {"campaign", "base", "fault", "detector"}
    for key in data:
        if key not in known:
            raise CampaignSpecError(
                f"{path}: unknown table {key!r}; valid: {', '.join(sorted(known))}"
            )
    head = data.get("campaign", {})
    if not isinstance(head, Mapping):
        raise CampaignSpecError(
            f"{path}: campaign: expected a table [campaign], got {type(head).__name__}"
        )
    head_keys = {"name", "seeds", "calibrate", "metrics", "match_far"}
    for key in head:
        if key not in head_keys:
            raise CampaignSpecError(
                f"{path}: campaign.{key}: unknown key; valid: {', '.join(sorted(head_keys))}"
            )
    seeds = _as_list(head.get("seeds", [0]))
    if not seeds or not all(
        isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in seeds
    ):
        raise CampaignSpecError(f"{path}: campaign.seeds must be a non-empty list of integers >= 0")
    cal = _calibration_window(head.get("calibrate", "0s:2s"), f"{path}: campaign.calibrate")
    match_far = DEFAULT_MATCH_FAR
    if "match_far" in head:
        from imufdi_cli.report import parse_far

        try:
            match_far = parse_far(str(head["match_far"]))
        except ImufdiError as err:
            raise CampaignSpecError(f"{path}: campaign.match_far: {err}") from err
    metrics = [str(m) for m in _as_list(head.get("metrics", DEFAULT_METRICS))]
    for metric in metrics:
        if metric not in METRIC_NAMES:
            raise CampaignSpecError(
                f"{path}: campaign.metrics: unknown metric {metric!r}; valid: {', '.join(METRIC_NAMES)}"
            )

    bases: list[dict[str, Any]] = []
    base_names: list[str] = []
    base_cals: list[list[float | None] | None] = []
    arrays: list[Any] = []
    durations: list[float] = []  # log length of each base, s (faults must start inside)
    for i, table in enumerate(_as_list(data.get("base", []))):
        where = f"{path}: base[{i}]"
        if not isinstance(table, Mapping):
            raise CampaignSpecError(f"{where}: expected a table")
        unknown = set(table) - {"preset", "options", "files", "calibrate", "name"}
        if unknown:
            raise CampaignSpecError(
                f"{where}: unknown key {sorted(unknown)[0]!r};"
                " valid: calibrate, files, name, options, preset"
            )
        base_cal = (
            _calibration_window(table["calibrate"], f"{where}.calibrate")
            if "calibrate" in table
            else None
        )
        if ("preset" in table) == ("files" in table):
            raise CampaignSpecError(f"{where}: give exactly one of preset or files")
        if "preset" in table:
            name = str(table["preset"])
            if name not in PRESETS:
                raise CampaignSpecError(
                    f"{where}: unknown preset {name!r}; valid: {', '.join(sorted(PRESETS))}"
                )
            raw_options = table.get("options", {})
            if not isinstance(raw_options, Mapping):
                raise CampaignSpecError(
                    f"{where}.options: expected a table of simulate options"
                    f' (e.g. options = {{ duration = "10s" }}), got {raw_options!r}'
                )
            options = {str(k): v for k, v in raw_options.items()}
            try:
                config = config_from_options(name, seed=0, **options)
            except ImufdiError as err:
                raise CampaignSpecError(f"{where}: {err}") from err
            bases.append({"preset": name, "options": options})
            base_names.append(str(table.get("name", name)))
            base_cals.append(base_cal)
            arrays.append(config.array)
            # as `imufdi inject` measures a log: first to last sample
            durations.append(max(config.n_samples - 1, 0) / config.rate_hz)
        else:
            matched: list[str] = []
            for pattern in _as_list(table["files"]):
                pattern = str(pattern)
                full = pattern if os.path.isabs(pattern) else str(path.parent / pattern)
                found = sorted(glob.glob(full))
                if not found:
                    raise CampaignSpecError(f"{where}: no file matches {pattern!r}")
                matched += found
            for file in matched:
                try:
                    array, block = _read_base(os.path.abspath(file))
                except ImufdiError as err:
                    raise CampaignSpecError(f"{where}: unreadable base log {file}: {err}") from err
                if len(block) == 0:
                    raise CampaignSpecError(
                        f"{where}: base log {file} holds no aligned IMU samples"
                    )
                bases.append({"file": os.path.abspath(file)})
                base_names.append(str(table.get("name", os.path.basename(file))))
                base_cals.append(base_cal)
                arrays.append(array)
                durations.append((int(block.t_ns[-1]) - int(block.t_ns[0])) * 1e-9)
    if not bases:
        raise CampaignSpecError(f"{path}: needs at least one [[base]] (preset or files)")

    def scope(table: Mapping[str, Any], where: str) -> set[int]:
        """Indices of the bases a [[fault]]/[[detector]] applies to (``bases`` key)."""
        if "bases" not in table:
            return set(range(len(bases)))
        chosen: set[int] = set()
        for label in _as_list(table["bases"]):
            hits = {k for k, n in enumerate(base_names) if n == str(label)}
            if not hits:
                raise CampaignSpecError(
                    f"{where}.bases: unknown base {label!r}; valid: {', '.join(sorted(set(base_names)))}"
                )
            chosen |= hits
        return chosen

    fault_sets: list[tuple[list[str], set[int]]] = []
    jitter_of: dict[str, float] = {}
    for i, table in enumerate(_as_list(data.get("fault", []))):
        where = f"{path}: fault[{i}]"
        if not isinstance(table, Mapping):
            raise CampaignSpecError(f"{where}: expected a table")
        where_bases = scope(table, where)
        grid = {k: v for k, v in table.items() if k != "bases"}
        jitter = _jitter_of(grid, where)
        for spec in _fault_specs(grid, where):
            fault_sets.append(([spec], where_bases))
            if jitter:
                jitter_of[spec] = jitter
    if not fault_sets:
        raise CampaignSpecError(f"{path}: the fault matrix is empty; add [[fault]] tables")

    detectors: list[tuple[str, dict[str, Any], list[float | None] | None, set[int]]] = []
    for i, table in enumerate(_as_list(data.get("detector", []))):
        where = f"{path}: detector[{i}]"
        if not isinstance(table, Mapping) or "name" not in table:
            raise CampaignSpecError(f"{where}: needs name")
        unknown = set(table) - {"name", "params", "calibrate", "bases"}
        if unknown:
            raise CampaignSpecError(
                f"{where}: unknown key {sorted(unknown)[0]!r}; valid: bases, calibrate, name, params"
            )
        det_bases = scope(table, where)
        name = str(table["name"])
        if name not in DETECTORS:
            raise CampaignSpecError(
                f"{where}: unknown detector {name!r}; valid: {', '.join(sorted(DETECTORS))}"
            )
        det_cal = (
            _calibration_window(table["calibrate"], f"{where}.calibrate")
            if "calibrate" in table
            else None
        )
        params_table = table.get("params", {})
        if not isinstance(params_table, Mapping):
            raise CampaignSpecError(f"{where}.params: expected a table of name = value or list")
        for params in _grid(dict(params_table)):
            try:
                make_detector(name, params)
            except ImufdiError as err:
                raise CampaignSpecError(f"{where}: {err}") from err
            detectors.append((name, params, det_cal, det_bases))
    if not detectors:
        raise CampaignSpecError(f"{path}: needs at least one [[detector]]")

    for index, (base, array) in enumerate(zip(bases, arrays)):
        assert isinstance(array, ArrayConfig)
        for specs, fault_bases in fault_sets:
            if index not in fault_bases:
                continue
            for spec in specs:
                try:
                    # the same checks as `imufdi inject`, including `at` inside the log
                    validate_faults(
                        [parse_fault_spec(spec, array)], array, log_duration_s=durations[index]
                    )
                except ImufdiError as err:
                    label = base.get("preset") or base.get("file")
                    raise CampaignSpecError(f"{path}: base {label}: {err}") from err

    runs = []
    for (index, (base, base_cal)), (specs, fault_bases), (
        det,
        params,
        det_cal,
        det_bases,
    ), seed in itertools.product(enumerate(zip(bases, base_cals)), fault_sets, detectors, seeds):
        if index not in fault_bases or index not in det_bases:
            continue
        window = det_cal or base_cal or cal  # detector over base over campaign
        desc: dict[str, Any] = {
            "base": base,
            "seed": int(seed),
            "faults": specs,
            "detector": det,
            "params": params,
            "calibrate": window,
        }
        if any(spec in jitter_of for spec in specs):
            desc["at_jitter"] = [jitter_of.get(spec) for spec in specs]
        if match_far != DEFAULT_MATCH_FAR:
            desc["match_far"] = match_far
        runs.append(desc)
    for index, name in enumerate(base_names):
        if not any(run["base"] is bases[index] for run in runs):
            raise CampaignSpecError(
                f"{path}: base {name!r} pairs with no [[fault]] and [[detector]]; check their bases"
            )
    return CampaignSpec(
        name=str(head.get("name", path.stem)), runs=runs, metrics=metrics, source=str(path)
    )


def run_key(desc: Mapping[str, Any]) -> str:
    """Stable key of a run: SHA-256 of its canonical JSON (first 20 hex digits)."""
    text = json.dumps(desc, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:20]


# --- one run ---------------------------------------------------------------------------


@lru_cache(maxsize=8)
def _read_base(path: str) -> tuple[Any, Any]:
    from imufdi_cli.mcapio import read_array

    return read_array(path)


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


def _execute(desc: Mapping[str, Any]) -> dict[str, Any]:
    from imufdi_cli.detect import calibration_window_ns, decision_positions, lookahead_of
    from imufdi_cli.detectors import make_detector
    from imufdi_cli.faults import FaultInjector, parse_fault_spec
    from imufdi_cli.log import iter_blocks
    from imufdi_cli.metrics import MetricsAccumulator
    from imufdi_cli.simulate import config_from_options, simulate_block

    base = desc["base"]
    seed = int(desc["seed"])
    if "preset" in base:
        config = config_from_options(base["preset"], seed=seed, **base.get("options", {}))
        array, block = simulate_block(config)
    else:
        array, block = _read_base(base["file"])
    specs, onsets = jittered_specs(desc["faults"], desc.get("at_jitter"), seed, array)
    faults = [parse_fault_spec(spec, array) for spec in specs]
    t0 = int(block.t_ns[0])
    injector = FaultInjector(faults, array, seed=seed, t0_ns=t0)
    faulty = injector.apply_block(block)
    detector = make_detector(desc["detector"], desc["params"])
    cal_start, cal_end = desc["calibrate"]
    window = calibration_window_ns(t0, int(faulty.t_ns[-1]), cal_start, cal_end)
    assert window is not None
    keep = (faulty.t_ns >= window[0]) & (faulty.t_ns < window[1])
    detector.fit(faulty.mask(keep), array)
    lookahead = lookahead_of(detector)
    accumulators: dict[str, MetricsAccumulator] = {}
    emitted: dict[str, int] = {}
    passed = 0

    def score(outputs: Mapping[str, Any]) -> None:
        for sensor_type, out in outputs.items():
            if sensor_type not in accumulators:
                ids = array.sensor_ids(sensor_type)
                windows = []
                for fault in faults:
                    if fault.sensor_type != sensor_type:
                        continue
                    columns = [ids.index(s) for s in fault.sensors if s in ids]
                    end = None if fault.until_ns is None else t0 + fault.until_ns
                    windows.append(FaultWindow(fault.id, tuple(columns), t0 + fault.at_ns, end))
                accumulators[sensor_type] = MetricsAccumulator(
                    len(ids), windows, calibration_ns=(window[0], window[1])
                )
                emitted[sensor_type] = 0
            rows = len(out)
            first = emitted[sensor_type]
            positions = decision_positions(first, rows, passed, lookahead)
            accumulators[sensor_type].update(
                faulty.t_ns[first : first + rows],
                out.alarm,
                out.isolated,
                decided_ns=faulty.t_ns[positions],
                isolated_set=out.isolated_set,
                statistic=out.statistic,
                threshold=out.threshold,
                scores=out.scores,
            )
            emitted[sensor_type] = first + rows

    for part in iter_blocks(faulty, BLOCK_SAMPLES):
        passed += len(part)
        score(detector.process(part))
    score(detector.flush())
    target = float(desc.get("match_far", DEFAULT_MATCH_FAR))
    figures: dict[str, Any] = {}
    for sensor_type, acc in accumulators.items():
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


# --- executors -------------------------------------------------------------------------


class _Executor:
    """submit(desc) -> future-like; results streamed back with as_completed semantics."""

    def run(self, runs: Sequence[dict[str, Any]]) -> Iterator[dict[str, Any]]:
        raise NotImplementedError

    def close(self) -> None:
        pass


@contextmanager
def worker_thread_env() -> Iterator[None]:
    """Set :data:`WORKER_THREAD_ENV` in ``os.environ`` for the block (restored after).

    Worker processes started inside the block (spawned pool workers, dask nannies) inherit
    it before they import numpy, so each uses one BLAS thread.
    """
    saved = {name: os.environ.get(name) for name in WORKER_THREAD_ENV}
    os.environ.update(WORKER_THREAD_ENV)
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def _init_worker(parent_pid: int) -> None:
    """Pool worker initializer: one BLAS thread, and exit when the parent is gone.

    A campaign process killed with SIGKILL cannot stop its pool; the watchdog makes the
    orphaned workers exit instead of waiting forever for work.
    """
    os.environ.update(WORKER_THREAD_ENV)

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(0.5)
        os._exit(1)

    threading.Thread(target=watch, name="imufdi-parent-watchdog", daemon=True).start()


class LocalExecutor(_Executor):
    """A process pool on this machine (``--jobs``); ``jobs=1`` runs in this process.

    Workers are *spawned* (fresh interpreters) with :data:`WORKER_THREAD_ENV` set before
    they import numpy; at most ``2 * jobs`` runs are in flight, so an interruption loses
    little.
    """

    def __init__(self, jobs: int, *, pool: bool | None = None) -> None:
        if jobs < 1:
            raise UsageError(f"--jobs must be >= 1, got {jobs}")
        self.jobs = jobs
        self.pool = pool  # None: a pool when jobs > 1; True/False forces it (benchmarks)

    def run(self, runs: Sequence[dict[str, Any]]) -> Iterator[dict[str, Any]]:
        use_pool = self.jobs > 1 and len(runs) > 1 if self.pool is None else self.pool
        if not use_pool:
            for desc in runs:
                yield execute_run(desc)
            return
        import multiprocessing

        context = multiprocessing.get_context("spawn")
        with worker_thread_env():
            pool = ProcessPoolExecutor(
                max_workers=min(self.jobs, len(runs)),
                mp_context=context,
                initializer=_init_worker,
                initargs=(os.getpid(),),
            )
            try:
                pending: set[Future[dict[str, Any]]] = set()
                queue = iter(runs)
                for desc in itertools.islice(queue, 2 * self.jobs):
                    pending.add(pool.submit(execute_run, desc))
                while pending:
                    done, pending = wait(pending, return_when=FIRST_COMPLETED)
                    for future in done:
                        nxt = next(queue, None)
                        if nxt is not None:
                            pending.add(pool.submit(execute_run, nxt))
                        yield future.result()
            finally:
                pool.shutdown(wait=True, cancel_futures=True)


class DaskExecutor(_Executor):
    """dask.distributed: ``tcp://host:port`` (an existing scheduler) or ``local:N``
    (a LocalCluster of N single-threaded worker processes on loopback)."""

    def __init__(self, scheduler: str) -> None:
        try:
            from dask.distributed import Client, LocalCluster
        except ImportError as err:
            raise UsageError(
                "--scheduler needs dask.distributed: pip install 'imufdi-cli[dask]'"
            ) from err
        self.cluster = None
        if scheduler.startswith("local:"):
            try:
                workers = int(scheduler.split(":", 1)[1])
                if workers < 1:
                    raise ValueError
            except ValueError:
                raise UsageError(
                    f"--scheduler {scheduler!r}: local:N needs N >= 1 workers"
                ) from None
            with worker_thread_env():
                self.cluster = LocalCluster(
                    n_workers=workers,
                    threads_per_worker=1,
                    processes=True,
                    host="127.0.0.1",
                    dashboard_address=None,
                )
            self.client = Client(self.cluster)
        elif scheduler.startswith("tcp://"):
            try:
                self.client = Client(scheduler, timeout=20)
            except OSError as err:
                raise UsageError(f"--scheduler {scheduler}: cannot connect ({err})") from err
        else:
            raise UsageError(
                f"--scheduler {scheduler!r}: valid forms are tcp://HOST:PORT and local:N"
            )

    def run(self, runs: Sequence[dict[str, Any]]) -> Iterator[dict[str, Any]]:
        from dask.distributed import as_completed

        futures = [self.client.submit(execute_run, desc, pure=False) for desc in runs]
        for future in as_completed(futures):
            yield future.result()

    def close(self) -> None:
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()


# --- campaign --------------------------------------------------------------------------


@dataclass
class CampaignResult:
    directory: str
    total: int
    executed: int
    skipped: int
    failed: int
    rows: list[dict[str, Any]] = field(default_factory=list)
    summary: dict[str, Any] = field(default_factory=dict)
    seconds: float = 0.0
    results: list[dict[str, Any]] = field(default_factory=list)


#: Files a campaign writes in its results directory (besides runs/<key>.json).
RESULT_FILES = ("runs.csv", "summary.json", "summary.md", "detection_probability.png")
#: Lock file in the results directory: one campaign at a time per directory.
LOCK_NAME = ".imufdi-campaign.lock"


@contextmanager
def results_lock(out: Path) -> Iterator[None]:
    """Hold an exclusive lock on a results directory for the block.

    The lock is an ``flock`` on ``<out>/.imufdi-campaign.lock``, which holds the PID and
    host of its holder. The kernel releases it when the holder exits, however it exits
    (SIGKILL included), so a lock file left by a dead campaign is simply taken over.

    Raises
    ------
    UsageError
        Another live campaign holds the lock (the message names its PID).
    """
    import fcntl
    import socket

    path = out / LOCK_NAME
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o666)
    except OSError as err:
        raise UsageError(f"-o {out}: cannot create the lock file {path} ({err.strerror})") from err
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 200, 0).decode("utf-8", "replace").split()
            who = (
                f"pid {holder[0]}" + (f" on {holder[1]}" if len(holder) > 1 else "")
                if holder
                else "a process that is starting"
            )
            raise UsageError(
                f"-o {out}: another campaign ({who}) is running on this results directory"
                f" (lock {path}); wait for it to finish or choose another directory"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()} {socket.gethostname()}\n".encode(), 0)
        yield
    finally:
        os.close(fd)  # releases the lock


def _write_json_atomic(path: Path, data: Any, *, sweep: bool = True) -> None:
    write_text(str(path), json.dumps(data, sort_keys=True, default=_jsonable) + "\n", sweep=sweep)


def _jsonable(value: Any) -> Any:
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (np.floating,)):
        return float(value)
    raise TypeError(type(value).__name__)


def run_campaign(
    spec: CampaignSpec,
    results_dir: str | Path,
    *,
    jobs: int | None = None,
    scheduler: str | None = None,
    resume: bool = False,
    progress: Callable[[int, int, dict[str, Any] | None], None] | None = None,
) -> CampaignResult:
    """Execute a campaign and write runs/, runs.csv, summary.json, summary.md.

    ``progress(done, total, result)`` is called after each finished run.
    """
    start = time.perf_counter()
    out = Path(results_dir)
    if out.exists() and not out.is_dir():
        raise UsageError(f"-o {out}: exists and is not a directory")
    check_outputs(
        [spec.source, *(r["base"]["file"] for r in spec.runs if "file" in r["base"])],
        [(f"-o {out}", out / name) for name in RESULT_FILES],
    )
    _check_fresh(out, resume)
    executor: _Executor
    if scheduler:
        executor = DaskExecutor(scheduler)  # a bad address fails before anything is written
    else:
        executor = LocalExecutor(jobs or os.cpu_count() or 1)
    try:
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise UsageError(f"-o {out}: cannot create the directory ({err.strerror})") from err
        with results_lock(out):
            _check_fresh(out, resume)  # again: another campaign may have finished meanwhile
            return _run_locked(spec, out, executor, resume=resume, progress=progress, start=start)
    finally:
        executor.close()


def _check_fresh(out: Path, resume: bool) -> None:
    """Without --resume, refuse a results directory that already holds run results."""
    runs_dir = out / "runs"
    existing = list(runs_dir.glob("*.json")) if runs_dir.is_dir() else []
    if existing and not resume:
        raise UsageError(
            f"{out} already holds {len(existing)} run results; use --resume to continue"
            " or choose another directory"
        )


def _run_locked(
    spec: CampaignSpec,
    out: Path,
    executor: _Executor,
    *,
    resume: bool,
    progress: Callable[[int, int, dict[str, Any] | None], None] | None,
    start: float,
) -> CampaignResult:
    """The campaign proper, with the results directory locked by this process."""
    runs_dir = out / "runs"
    existing = sorted(runs_dir.glob("*.json")) if runs_dir.is_dir() else []
    keyed = {run_key(desc): desc for desc in spec.runs}
    done_keys = {p.stem for p in existing} & set(keyed) if resume else set()
    todo = [desc for key, desc in keyed.items() if key not in done_keys]
    total = len(keyed)
    executed = 0
    runs_dir.mkdir(parents=True, exist_ok=True)
    # left by a campaign killed while writing (safe: we hold the directory's lock)
    for stale in runs_dir.glob(".*.json.*.tmp"):
        stale.unlink(missing_ok=True)
    if progress:
        progress(len(done_keys), total, None)
    for result in executor.run(todo):
        # runs/ was swept once above: no directory listing per result
        _write_json_atomic(runs_dir / f"{result['key']}.json", result, sweep=False)
        executed += 1
        if progress:
            progress(len(done_keys) + executed, total, result)
    results = []
    for key in keyed:
        path = runs_dir / f"{key}.json"
        if path.exists():
            results.append(json.loads(path.read_text(encoding="utf-8")))
    rows = _rows(results)
    summary = summarize(spec, results)
    write_text(str(out / "runs.csv"), _rows_csv(rows))
    _write_json_atomic(out / "summary.json", summary)
    write_text(str(out / "summary.md"), summary_markdown(summary))
    try:
        plot_curves(summary, out)
    except UsageError:
        pass  # matplotlib not installed: figures are optional
    return CampaignResult(
        directory=str(out),
        total=total,
        executed=executed,
        skipped=len(done_keys),
        failed=sum(1 for r in results if not r["ok"]),
        rows=rows,
        summary=summary,
        seconds=time.perf_counter() - start,
        results=results,
    )


_AMPLITUDE_KEYS = ("amp", "rate", "factor", "sigma")


def _fault_model_amp(specs: Sequence[str]) -> tuple[str, str]:
    """Model and amplitude-like parameter of a run's (first) fault spec, for grouping."""
    spec = specs[0]
    model, rest = spec.split(":", 1)
    parts = rest.split(",")
    values = dict(p.split("=", 1) for p in parts[1:] if "=" in p)
    amp = next((values[k] for k in _AMPLITUDE_KEYS if values.get(k)), "")
    return model, amp


def _fault_label(specs: Sequence[str]) -> tuple[str, str]:
    """The run's (first) fault spec without its amplitude, and its sensor: runs that differ
    only in amplitude share the label (one curve), faults on different sensors do not."""
    spec = specs[0]
    head, *items = spec.split(",")
    kept = [it for it in items if it.split("=", 1)[0] not in _AMPLITUDE_KEYS]
    sensor = head.split(":", 1)[1] if ":" in head else ""
    return ",".join([head, *kept]), sensor


def _amplitude_number(amplitude: str) -> tuple[float | None, str]:
    """``"0.9deg/s"`` -> ``(0.9, "deg/s")``: the spec's number and unit as written."""
    import re

    match = re.match(r"^\s*([+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)\s*(.*?)\s*$", amplitude)
    if not match:
        return None, ""
    return float(match.group(1)), match.group(2)


def _base_label(base: Mapping[str, Any]) -> str:
    if "preset" in base:
        opts = ",".join(f"{k}={v}" for k, v in sorted(base.get("options", {}).items()))
        return base["preset"] + (f"[{opts}]" if opts else "")
    return os.path.basename(base["file"])


def _rows(results: Iterable[Mapping[str, Any]]) -> list[dict[str, Any]]:
    rows = []
    for r in results:
        run = r["run"]
        model, amp = _fault_model_amp(run["faults"])
        label, sensor = _fault_label(run["faults"])
        onsets: list[Any] = []
        if r["ok"]:
            first: Mapping[str, Any] = next(iter(r["metrics"].values()), {})
            onsets = first.get("onsets_s") or []
        common = {
            "key": r["key"],
            "base": _base_label(run["base"]),
            "seed": run["seed"],
            "faults": ";".join(run["faults"]),
            "fault": label,
            "sensor": sensor,
            "onset_s": ";".join("" if o is None else f"{o:.6f}" for o in onsets),
            "model": model,
            "amplitude": amp,
            "detector": run["detector"],
            "params": json.dumps(run["params"], sort_keys=True),
            "ok": r["ok"],
            "error": r.get("error", ""),
        }
        if not r["ok"]:
            rows.append(common | {"sensor_type": ""})
            continue
        for sensor_type, figures in sorted(r["metrics"].items()):
            row = common | {"sensor_type": sensor_type}
            row |= {name: figures.get(name) for name in METRIC_NAMES}
            row["target_far"] = figures.get("target_far")
            rows.append(row)
    return rows


def _rows_csv(rows: Sequence[Mapping[str, Any]]) -> str:
    fields = [
        "key",
        "base",
        "seed",
        "faults",
        "fault",
        "sensor",
        "onset_s",
        "model",
        "amplitude",
        "detector",
        "params",
        "sensor_type",
        "ok",
        "error",
        *METRIC_NAMES,
        "target_far",
    ]
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=fields, lineterminator="\n")
    writer.writeheader()
    for row in sorted(
        rows,
        key=lambda r: (
            r["base"],
            r["detector"],
            r["params"],
            r["faults"],
            r["seed"],
            r["sensor_type"],
        ),
    ):
        writer.writerow({k: ("" if row.get(k) is None else row.get(k)) for k in fields})
    return buffer.getvalue()


def _amplitude_order(amplitude: str, sensor_type: str) -> tuple[bool, float, str]:
    si = _amplitude_si(amplitude, sensor_type)
    return (si is None, 0.0 if si is None else si, amplitude)


def summarize(spec: CampaignSpec, results: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Means and spreads over seeds per base x detector x params x fault (spec without its
    amplitude, so faults on different sensors stay apart) x amplitude x sensor type,
    amplitudes in numeric order, plus detection probability against amplitude."""
    groups: dict[tuple[str, ...], list[dict[str, Any]]] = {}
    for row in _rows(results):
        if not row["ok"]:
            continue
        sensor = row["sensor"].split(".")
        fault_type = sensor[1] if len(sensor) > 1 else ""
        if row["sensor_type"] != fault_type:
            continue  # score each run on the sensor type its fault acts on
        key = (
            row["base"],
            row["detector"],
            row["params"],
            row["fault"],
            row["amplitude"],
            row["sensor_type"],
        )
        groups.setdefault(key, []).append(row)
    table = []
    ordered = sorted(
        groups.items(),
        key=lambda item: (item[0][:4], item[0][5], _amplitude_order(item[0][4], item[0][5])),
    )
    for (base, det, params, fault, amp, sensor_type), rows in ordered:
        first = rows[0]
        entry: dict[str, Any] = {
            "base": base,
            "detector": det,
            "params": json.loads(params),
            "fault": fault,
            "sensor": first["sensor"],
            "model": first["model"],
            "amplitude": amp,
            "sensor_type": sensor_type,
            "runs": len(rows),
        }
        for metric in spec.metrics:
            mean, std, count = mean_metrics([r.get(metric) for r in rows])
            entry[metric] = {"mean": mean, "std": std, "n": count}
        targets = {float(r["target_far"]) for r in rows if r.get("target_far") is not None}
        if targets:
            entry["target_far"] = sorted(targets)[0]
        table.append(entry)
    failures = [{"key": r["key"], "error": r.get("error", "")} for r in results if not r["ok"]]
    return {
        "name": spec.name,
        "spec": spec.source,
        "runs": len(results),
        "failed": len(failures),
        "metrics": spec.metrics,
        "groups": table,
        "curves": detection_curves(table),
        "failures": failures[:50],
    }


def _amplitude_si(amplitude: str, sensor_type: str) -> float | None:
    """Amplitude text -> SI float (``"0.9deg/s"`` on gyro -> rad/s); bare numbers as is."""
    from imufdi_cli.units import parse_quantity, rate_dimension, sensor_dimension

    for dimension in (sensor_dimension, rate_dimension):  # amplitudes, then drift rates
        try:
            return float(parse_quantity(amplitude, dimension(sensor_type)))
        except ImufdiError:
            continue
    try:
        return float(amplitude)
    except ValueError:
        return None


def detection_curves(groups: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Detection probability against amplitude, one curve per base x detector x params x
    fault (spec without amplitude) x sensor type, points sorted by SI amplitude and given
    in the spec's own units too (``amplitude_value``, ``unit`` when all points share one)."""
    curves: dict[tuple[str, str, str, str, str], list[dict[str, Any]]] = {}
    models: dict[tuple[str, str, str, str, str], str] = {}
    for g in groups:
        stat = g.get("detection_probability")
        if stat is None:
            continue
        fault = g.get("fault", g["model"])
        key = (
            g["base"],
            g["detector"],
            json.dumps(g["params"], sort_keys=True),
            fault,
            g["sensor_type"],
        )
        models[key] = g["model"]
        value, unit = _amplitude_number(g["amplitude"])
        curves.setdefault(key, []).append(
            {
                "amplitude": g["amplitude"],
                "amplitude_si": _amplitude_si(g["amplitude"], g["sensor_type"]),
                "amplitude_value": value,
                "amplitude_unit": unit,
                "mean": stat["mean"],
                "std": stat["std"],
                "n": stat["n"],
            }
        )
    out = []
    for key, points in sorted(curves.items()):
        base, det, params, fault, sensor_type = key
        points.sort(key=lambda p: (p["amplitude_si"] is None, p["amplitude_si"] or 0.0))
        units = {p["amplitude_unit"] for p in points}
        out.append(
            {
                "base": base,
                "detector": det,
                "params": json.loads(params),
                "fault": fault,
                "model": models[key],
                "sensor_type": sensor_type,
                "unit": units.pop() if len(units) == 1 else None,
                "points": points,
            }
        )
    return out


def summary_markdown(summary: Mapping[str, Any]) -> str:
    metrics = summary["metrics"]
    scale = {
        m: (
            100.0
            if m
            in {
                "far",
                "mar",
                "accuracy",
                "fir",
                "isolation_accuracy",
                "detection_rate",
                "detection_probability",
                "alarm_rate",
                "far_calibration",
                "rate_after_first_detection",
                "mar_at_far",
                "fir_at_far",
            }
            else 1.0
        )
        for m in metrics
    }
    head = ["base", "detector", "params", "fault", "amplitude", "type", "runs"] + [
        f"{m} {'%' if scale[m] == 100.0 else ''}".strip() for m in metrics
    ]
    lines = [
        f"# Campaign {summary['name']}",
        "",
        f"{summary['runs']} runs, {summary['failed']} failed. Mean ± standard deviation over seeds.",
        "FAR outside the calibration window; delays at decision time; `*_at_far` with the"
        " threshold scaled to the matched FAR"
        + (
            f" ({100 * summary['groups'][0]['target_far']:g} %)."
            if summary["groups"] and "target_far" in summary["groups"][0]
            else "."
        ),
        "",
        "| " + " | ".join(head) + " |",
        "|" + "|".join("---" for _ in head) + "|",
    ]
    for g in summary["groups"]:
        cells = [
            g["base"],
            g["detector"],
            ", ".join(f"{k}={v}" for k, v in g["params"].items()) or "default",
            g.get("fault", g["model"]),
            g["amplitude"],
            g["sensor_type"],
            str(g["runs"]),
        ]
        for m in metrics:
            stat = g[m]
            if stat["mean"] is None:
                cells.append("undefined")
            elif stat["std"] is None:
                cells.append(f"{stat['mean'] * scale[m]:.3g}")
            else:
                cells.append(f"{stat['mean'] * scale[m]:.3g} ± {stat['std'] * scale[m]:.2g}")
        lines.append("| " + " | ".join(cells) + " |")
    curves = summary.get("curves") or []
    if curves:
        lines += [
            "",
            "## Detection probability against amplitude",
            "",
            "| base | detector | params | fault | type | amplitude: probability % |",
            "|---|---|---|---|---|---|",
        ]
        for c in curves:
            points = ", ".join(
                f"{p['amplitude'] or '-'}: "
                + ("undefined" if p["mean"] is None else f"{100.0 * p['mean']:.3g}")
                for p in c["points"]
            )
            params = ", ".join(f"{k}={v}" for k, v in c["params"].items()) or "default"
            lines.append(
                f"| {c['base']} | {c['detector']} | {params} | {c.get('fault', c['model'])}"
                f" | {c['sensor_type']} | {points} |"
            )
    if summary["failures"]:
        lines += ["", "## Failed runs", ""]
        lines += [f"- `{f['key']}`: {f['error']}" for f in summary["failures"]]
    return "\n".join(lines) + "\n"


def plot_curves(summary: Mapping[str, Any], out: Path) -> None:
    """``detection_probability.png``: one panel per base x fault model x sensor type, with
    the per-event detection probability (solid) and, when MAR is aggregated, the per-sample
    detection rate 1 - MAR (dashed) of each detector against the SI amplitude (plot extra).
    """
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as err:
        raise UsageError("plots need matplotlib") from err
    rates: dict[tuple[str, str, str, str, str], float] = {}
    for g in summary["groups"]:
        mar = g.get("mar")
        if mar is not None and mar["mean"] is not None:
            params = json.dumps(g["params"], sort_keys=True)
            key = (g["base"], g["detector"], params, g.get("fault", g["model"]), g["amplitude"])
            rates[key] = 1.0 - mar["mean"]
    panels: dict[tuple[str, str, str], list[dict[str, Any]]] = {}
    for c in summary.get("curves", []):
        panels.setdefault((c["base"], c.get("fault", c["model"]), c["sensor_type"]), []).append(c)
    if not panels:
        return
    fig, axes = plt.subplots(
        1, len(panels), figsize=(4.2 * len(panels), 3.8), squeeze=False, constrained_layout=True
    )
    for ax, ((base, model, sensor_type), curves) in zip(axes[0], sorted(panels.items())):
        for index, c in enumerate(curves):
            params = json.dumps(c["params"], sort_keys=True)
            label = c["detector"] + ("" if not c["params"] else " " + params)
            unit = c.get("unit")
            field = "amplitude_value" if unit is not None else "amplitude_si"
            points = [p for p in c["points"] if p.get(field) is not None]
            xs = [p[field] for p in points]
            color = f"C{index % 10}"
            probability = [np.nan if p["mean"] is None else p["mean"] for p in points]
            ax.plot(xs, probability, "o-", color=color, label=label)
            rate = [
                rates.get((base, c["detector"], params, model, p["amplitude"]), np.nan)
                for p in points
            ]
            ax.plot(xs, rate, "s--", color=color, alpha=0.7)
        ax.set_title(f"{base} · {model} · {sensor_type}", fontsize=9)
        units = {c.get("unit") for c in curves}
        unit = units.pop() if len(units) == 1 else None
        if unit is None:
            ax.set_xlabel("fault amplitude (SI)")
        else:
            ax.set_xlabel(f"fault amplitude, {unit}" if unit else "fault amplitude")
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    axes[0][0].set_ylabel("detection probability (solid), 1 - MAR (dashed)")
    try:
        with atomic_path(out / "detection_probability.png", suffix=".png") as tmp:
            fig.savefig(tmp, dpi=100)  # matplotlib takes the format from the extension
    finally:
        plt.close(fig)


# --- gates over the summary ------------------------------------------------------------


def evaluate_summary_gates(
    summary: Mapping[str, Any], gates: Sequence[str]
) -> list[tuple[str, bool, str]]:
    """``DETECTOR.TYPE.METRIC OP NUMBER`` on the group means; a gate fails when any group
    of that detector and type violates it (or its mean is undefined)."""
    from imufdi_cli.detectors import DETECTORS
    from imufdi_cli.errors import GateError
    from imufdi_cli.report import OPERATORS, parse_gate

    parsed = [parse_gate(g, DETECTORS) for g in gates]
    outcomes = []
    for gate in parsed:
        groups = [
            g
            for g in summary["groups"]
            if gate.detector in ("*", g["detector"]) and gate.sensor_type in ("*", g["sensor_type"])
        ]
        if not groups:
            raise GateError(
                f"--fail-if {gate.text!r}: no campaign results for {gate.detector}.{gate.sensor_type}"
            )
        for g in groups:
            stat = g.get(gate.metric)
            if stat is None:
                raise GateError(
                    f"--fail-if {gate.text!r}: metric {gate.metric!r} is not aggregated; add it to campaign.metrics"
                )
            label = f"{g['detector']}.{g['sensor_type']}.{gate.metric} [{g['base']} {g['model']} {g['amplitude']}]"
            if stat["mean"] is None:
                outcomes.append((label, True, f"{label} is undefined"))
                continue
            failed = OPERATORS[gate.op](stat["mean"], gate.value)
            outcomes.append(
                (
                    label,
                    failed,
                    f"{'FAILED' if failed else 'passed'}: {label} = {stat['mean']:.6g} (fail if {gate.op} {gate.value:g})",
                )
            )
    return outcomes


def check_all_failed(result: CampaignResult) -> None:
    """Raise :class:`CampaignFailedError` when every run of the campaign failed.

    Exit 4 when any run failed on an internal error (a bug), else 3 (the runs failed on
    their data). A campaign where only some runs failed succeeds: the failures are in
    ``summary.json``/``summary.md`` and counted on the console.
    """
    if not result.results or any(r["ok"] for r in result.results):
        return
    internal = any(_is_internal(r) for r in result.results)
    first = result.results[0]
    raise CampaignFailedError(
        f"all {len(result.results)} runs failed (first: run {first['key']}:"
        f" {first.get('error') or 'no message'});"
        f" details in {Path(result.directory) / 'summary.md'}",
        internal=internal,
    )


def _is_internal(result: Mapping[str, Any]) -> bool:
    """A failed run failed on a bug (not an imufdi error); older results: a traceback."""
    if result.get("ok"):
        return False
    return bool(result.get("internal", bool(result.get("traceback"))))


def run_campaign_cli(
    spec_path: str,
    results_dir: str,
    *,
    jobs: int | None,
    scheduler: str | None,
    resume: bool,
    gates: Sequence[str],
    console: Any,
) -> int:
    """What ``imufdi campaign`` does; returns the exit code (0, or 1 when a gate fails).

    Raises CampaignFailedError (exit 3, or 4 on internal errors) when every run failed.
    """
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeRemainingColumn,
    )

    from imufdi_cli.detectors import DETECTORS
    from imufdi_cli.report import parse_gate

    spec = load_spec(spec_path)
    for gate in gates:
        parse_gate(gate, DETECTORS)  # bad gates fail before any run
    with Progress(
        TextColumn("[bold]campaign[/] {task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("failed {task.fields[failed]}"),
        TimeRemainingColumn(),
        console=console,
        transient=False,
        disable=not console.is_terminal,  # a bar only on a terminal, never in logs/pipes
    ) as bar:
        task = bar.add_task(spec.name, total=len({run_key(r) for r in spec.runs}), failed=0)
        failed = 0

        def progress(done: int, total: int, result: dict[str, Any] | None) -> None:
            nonlocal failed
            if result is not None and not result["ok"]:
                failed += 1
            bar.update(task, completed=done, failed=failed)

        result = run_campaign(
            spec, results_dir, jobs=jobs, scheduler=scheduler, resume=resume, progress=progress
        )
    console.print(
        f"{result.total} runs ({result.executed} executed, {result.skipped} resumed, "
        f"{result.failed} failed) in {result.seconds:.1f} s -> {result.directory}"
    )
    check_all_failed(result)
    outcomes = evaluate_summary_gates(result.summary, gates)
    for _, failed_gate, message in outcomes:
        console.print(f"[{'red' if failed_gate else 'green'}]gate {message}[/]", markup=True)
    return 1 if any(f for _, f, _ in outcomes) else 0
