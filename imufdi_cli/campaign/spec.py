"""Campaign specs: parse and validate the TOML, expand it into run descriptions, key them."""

from __future__ import annotations

import glob
import hashlib
import itertools
import json
import os
from collections.abc import Mapping
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from imufdi_cli.errors import CampaignSpecError, ImufdiError
from imufdi_cli.metrics import (
    METRIC_NAMES,
)
from imufdi_cli.tomlfile import parse_toml

DEFAULT_METRICS = [
    "far",
    "mar",
    "accuracy",
    "fir",
    "detection_delay_s",
    "isolation_delay_s",
    "detection_probability",
    "mar_at_far",
    "detection_delay_at_far_s",
]


#: Target FAR of the ``*_at_far`` figures unless ``campaign.match_far`` says otherwise.
DEFAULT_MATCH_FAR = 0.01
#: Target of the ``*_at_budget`` figures, false alarm episodes per hour, unless
#: ``campaign.match_budget`` says otherwise.
DEFAULT_MATCH_BUDGET = 1.0


@dataclass
class CampaignSpec:
    """A parsed, validated campaign spec."""

    name: str
    runs: list[dict[str, Any]]
    metrics: list[str]
    source: str
    #: the matched budget's target, false episodes per hour (pooled over each detector's runs)
    match_budget: float = DEFAULT_MATCH_BUDGET


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


def _calibration_window(value: Any, where: str) -> list[float | None]:
    """``"START:END"`` (times from the log start) -> ``[start_s, end_s or None]``."""
    from imufdi_cli.units import parse_time_range

    try:
        start, end = parse_time_range(str(value), name=where)
    except ImufdiError as err:
        raise CampaignSpecError(str(err)) from err
    return [start, end]


def load_spec(path: str | Path) -> CampaignSpec:
    """Parse and validate a campaign spec; every problem is reported before any run.

    Raises
    ------
    CampaignSpecError
        One line naming the file and the key at fault (the first problem found, in the
        order: tables, ``[campaign]``, bases, faults, detectors, faults on each base,
        bases left without runs).
    """
    path = Path(path)
    data = _read_toml(path)
    for key in data:
        if key not in _TABLES:
            raise CampaignSpecError(
                f"{path}: unknown table {key!r}; valid: {', '.join(sorted(_TABLES))}"
            )
    head = _parse_head(data.get("campaign", {}), path)
    bases = _parse_bases(data.get("base", []), path)
    fault_sets = _parse_faults(data.get("fault", []), path, bases)
    detectors = _parse_detectors(data.get("detector", []), path, bases, head.false_alarms)
    _check_faults_fit_bases(path, bases, fault_sets)
    runs = _expand_runs(head, bases, fault_sets, detectors)
    used = {index for index, _ in runs}
    for index, base in enumerate(bases):
        if index not in used:
            raise CampaignSpecError(
                f"{path}: base {base.name!r} pairs with no [[fault]] and [[detector]]; check their bases"
            )
    return CampaignSpec(
        name=head.name,
        runs=[desc for _, desc in runs],
        metrics=head.metrics,
        source=str(path),
        match_budget=head.match_budget,
    )


_TABLES = {"campaign", "base", "fault", "detector"}
_HEAD_KEYS = {"name", "seeds", "calibrate", "metrics", "match_far", "match_budget", "false_alarms"}
_BASE_KEYS = {"preset", "options", "files", "calibrate", "name"}
_DETECTOR_KEYS = {"name", "params", "calibrate", "bases", "false_alarms"}

#: A calibration window ``[start_s, end_s or None]`` from the log start.
Window = list[float | None]


@dataclass
class _Head:
    """``[campaign]``: what applies to every run."""

    name: str
    seeds: list[int]
    calibrate: Window
    match_far: float
    metrics: list[str]
    match_budget: float = DEFAULT_MATCH_BUDGET
    false_alarms: float | None = None  # episodes per second, every detector's budget


@dataclass
class _Base:
    """One base log: its run description, label, window and what validation needs."""

    desc: dict[str, Any]
    name: str
    calibrate: Window | None
    array: Any  # ArrayConfig
    duration_s: float  # first to last sample, as `imufdi inject` measures a log


@dataclass
class _FaultSet:
    """The faults of one run (one spec string each), the bases they apply to and their
    ``at_jitter`` in seconds (None: no jitter)."""

    specs: list[str]
    bases: set[int]
    jitters: list[float | None]


@dataclass
class _Detector:
    name: str
    params: dict[str, Any]
    calibrate: Window | None
    bases: set[int]
    false_alarms: float | None = None  # episodes per second (None: the campaign's)


def _read_toml(path: Path) -> dict[str, Any]:
    try:
        text = path.read_text(encoding="utf-8")  # universal newlines, as before
    except OSError as err:
        raise CampaignSpecError(f"cannot read campaign spec {path}: {err.strerror}") from err
    except UnicodeDecodeError as err:
        raise CampaignSpecError(f"{path}: not valid TOML ({err})") from err
    return parse_toml(text, path, CampaignSpecError)


def _parse_head(head: Any, path: Path) -> _Head:
    """``[campaign]``: name, seeds, calibration window, matched FAR, metrics."""
    if not isinstance(head, Mapping):
        raise CampaignSpecError(
            f"{path}: campaign: expected a table [campaign], got {type(head).__name__}"
        )
    for key in head:
        if key not in _HEAD_KEYS:
            raise CampaignSpecError(
                f"{path}: campaign.{key}: unknown key; valid: {', '.join(sorted(_HEAD_KEYS))}"
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
    match_budget = DEFAULT_MATCH_BUDGET
    if "match_budget" in head:
        match_budget = episode_rate(head["match_budget"], f"{path}: campaign.match_budget") * 3600
        if not match_budget > 0:
            raise CampaignSpecError(
                f"{path}: campaign.match_budget: must be a rate > 0 such as 1/h,"
                f" got {head['match_budget']!r}"
            )
    false_alarms = None
    if "false_alarms" in head:
        false_alarms = episode_rate(head["false_alarms"], f"{path}: campaign.false_alarms")
    return _Head(
        str(head.get("name", path.stem)),
        [int(s) for s in seeds],
        cal,
        match_far,
        metrics,
        match_budget,
        false_alarms,
    )


def episode_rate(value: Any, where: str) -> float:
    """A rate of episodes such as ``"1/h"``, ``"0.1/h"`` or ``"5/min"`` (a bare number is
    per second) -> episodes per second, >= 0."""
    from imufdi_cli.units import parse_quantity

    try:
        rate = parse_quantity(str(value), "frequency", name=where)
    except ImufdiError as err:
        raise CampaignSpecError(f"{where}: {err}") from err
    if not rate >= 0 or not np.isfinite(rate):
        raise CampaignSpecError(f"{where}: must be a rate >= 0 such as 1/h, got {value!r}")
    return float(rate)


def _parse_bases(tables: Any, path: Path) -> list[_Base]:
    """Every ``[[base]]``: a seeded simulate preset, or one base per matching MCAP file."""
    bases: list[_Base] = []
    for i, table in enumerate(_as_list(tables)):
        where = f"{path}: base[{i}]"
        if not isinstance(table, Mapping):
            raise CampaignSpecError(f"{where}: expected a table")
        unknown = set(table) - _BASE_KEYS
        if unknown:
            raise CampaignSpecError(
                f"{where}: unknown key {sorted(unknown)[0]!r};"
                " valid: calibrate, files, name, options, preset"
            )
        cal = (
            _calibration_window(table["calibrate"], f"{where}.calibrate")
            if "calibrate" in table
            else None
        )
        if ("preset" in table) == ("files" in table):
            raise CampaignSpecError(f"{where}: give exactly one of preset or files")
        if "preset" in table:
            bases.append(_preset_base(table, cal, where))
        else:
            bases += _file_bases(table, cal, where, path)
    if not bases:
        raise CampaignSpecError(f"{path}: needs at least one [[base]] (preset or files)")
    return bases


def _preset_base(table: Mapping[str, Any], cal: Window | None, where: str) -> _Base:
    from imufdi_cli.simulate import PRESETS, config_from_options

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
    return _Base(
        desc={"preset": name, "options": options},
        name=str(table.get("name", name)),
        calibrate=cal,
        array=config.array,
        duration_s=max(config.n_samples - 1, 0) / config.rate_hz,
    )


def _file_bases(
    table: Mapping[str, Any], cal: Window | None, where: str, path: Path
) -> list[_Base]:
    """``files = [...]``: paths or globs relative to the spec file, each read once here."""
    matched: list[str] = []
    for pattern in _as_list(table["files"]):
        pattern = str(pattern)
        full = pattern if os.path.isabs(pattern) else str(path.parent / pattern)
        found = sorted(glob.glob(full))
        if not found:
            raise CampaignSpecError(f"{where}: no file matches {pattern!r}")
        matched += found
    bases = []
    for file in matched:
        try:
            array, block = read_base(os.path.abspath(file))
        except ImufdiError as err:
            raise CampaignSpecError(f"{where}: unreadable base log {file}: {err}") from err
        if len(block) == 0:
            raise CampaignSpecError(f"{where}: base log {file} holds no aligned IMU samples")
        bases.append(
            _Base(
                desc={"file": os.path.abspath(file)},
                name=str(table.get("name", os.path.basename(file))),
                calibrate=cal,
                array=array,
                duration_s=(int(block.t_ns[-1]) - int(block.t_ns[0])) * 1e-9,
            )
        )
    return bases


def _scope(table: Mapping[str, Any], where: str, bases: list[_Base]) -> set[int]:
    """Indices of the bases a [[fault]]/[[detector]] applies to (``bases`` key)."""
    if "bases" not in table:
        return set(range(len(bases)))
    names = [b.name for b in bases]
    chosen: set[int] = set()
    for label in _as_list(table["bases"]):
        hits = {k for k, n in enumerate(names) if n == str(label)}
        if not hits:
            raise CampaignSpecError(
                f"{where}.bases: unknown base {label!r}; valid: {', '.join(sorted(set(names)))}"
            )
        chosen |= hits
    return chosen


def _parse_faults(tables: Any, path: Path, bases: list[_Base]) -> list[_FaultSet]:
    """Every ``[[fault]]`` expanded over its lists: one single-fault set per combination."""
    fault_sets: list[_FaultSet] = []
    for i, table in enumerate(_as_list(tables)):
        where = f"{path}: fault[{i}]"
        if not isinstance(table, Mapping):
            raise CampaignSpecError(f"{where}: expected a table")
        where_bases = _scope(table, where, bases)
        grid = {k: v for k, v in table.items() if k != "bases"}
        jitter = _jitter_of(grid, where)
        for spec in _fault_specs(grid, where):
            fault_sets.append(_FaultSet([spec], where_bases, [jitter or None]))
    if not fault_sets:
        raise CampaignSpecError(f"{path}: the fault matrix is empty; add [[fault]] tables")
    return fault_sets


def _parse_detectors(
    tables: Any, path: Path, bases: list[_Base], false_alarms: float | None = None
) -> list[_Detector]:
    """Every ``[[detector]]`` expanded over its parameter grid, each point constructed once
    with its false-alarm budget (its own ``false_alarms``, else the campaign's), as
    ``detect --false-alarms`` sets it (unknown names, bad parameters and detectors without
    a budget fail here)."""
    from imufdi_cli.detectors import DETECTORS, make_detector
    from imufdi_cli.engine import with_budget

    detectors: list[_Detector] = []
    for i, table in enumerate(_as_list(tables)):
        where = f"{path}: detector[{i}]"
        if not isinstance(table, Mapping) or "name" not in table:
            raise CampaignSpecError(f"{where}: needs name")
        unknown = set(table) - _DETECTOR_KEYS
        if unknown:
            raise CampaignSpecError(
                f"{where}: unknown key {sorted(unknown)[0]!r};"
                " valid: bases, calibrate, false_alarms, name, params"
            )
        det_bases = _scope(table, where, bases)
        name = str(table["name"])
        if name not in DETECTORS:
            raise CampaignSpecError(
                f"{where}: unknown detector {name!r}; valid: {', '.join(sorted(DETECTORS))}"
            )
        cal = (
            _calibration_window(table["calibrate"], f"{where}.calibrate")
            if "calibrate" in table
            else None
        )
        budget = false_alarms
        if "false_alarms" in table:
            budget = episode_rate(table["false_alarms"], f"{where}.false_alarms")
        params_table = table.get("params", {})
        if not isinstance(params_table, Mapping):
            raise CampaignSpecError(f"{where}.params: expected a table of name = value or list")
        for params in _grid(dict(params_table)):
            try:
                make_detector(name, with_budget([(name, params)], budget)[0][1])
            except ImufdiError as err:
                raise CampaignSpecError(f"{where}: {err}") from err
            detectors.append(_Detector(name, params, cal, det_bases, budget))
    if not detectors:
        raise CampaignSpecError(f"{path}: needs at least one [[detector]]")
    return detectors


def _check_faults_fit_bases(path: Path, bases: list[_Base], fault_sets: list[_FaultSet]) -> None:
    """The checks of `imufdi inject` for every fault on every base it applies to
    (sensor in the array, ``at`` inside the log, ...)."""
    from imufdi_cli.faults import parse_fault_spec, validate_faults

    for index, base in enumerate(bases):
        for fault_set in fault_sets:
            if index not in fault_set.bases:
                continue
            for spec in fault_set.specs:
                try:
                    validate_faults(
                        [parse_fault_spec(spec, base.array)],
                        base.array,
                        log_duration_s=base.duration_s,
                    )
                except ImufdiError as err:
                    label = base.desc.get("preset") or base.desc.get("file")
                    raise CampaignSpecError(f"{path}: base {label}: {err}") from err


def _expand_runs(
    head: _Head, bases: list[_Base], fault_sets: list[_FaultSet], detectors: list[_Detector]
) -> list[tuple[int, dict[str, Any]]]:
    """Run descriptions (with their base index): base x fault set x detector x seed, for
    the combinations whose ``bases`` scopes agree. The calibration window is the
    detector's, else the base's, else the campaign's."""
    runs = []
    for (index, base), fault_set, det, seed in itertools.product(
        enumerate(bases), fault_sets, detectors, head.seeds
    ):
        if index not in fault_set.bases or index not in det.bases:
            continue
        desc: dict[str, Any] = {
            "base": base.desc,
            "seed": int(seed),
            "faults": fault_set.specs,
            "detector": det.name,
            "params": det.params,
            "calibrate": det.calibrate or base.calibrate or head.calibrate,
        }
        if any(fault_set.jitters):
            desc["at_jitter"] = fault_set.jitters
        if head.match_far != DEFAULT_MATCH_FAR:
            desc["match_far"] = head.match_far
        if det.false_alarms is not None:
            desc["false_alarms"] = det.false_alarms
        runs.append((index, desc))
    return runs


def run_key(desc: Mapping[str, Any]) -> str:
    """Stable key of a run: SHA-256 of its canonical JSON (first 20 hex digits)."""
    text = json.dumps(desc, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:20]


@lru_cache(maxsize=8)
def read_base(path: str) -> tuple[Any, Any]:
    """``(ArrayConfig, ImuBlock)`` of a base log file, read once per process (the spec
    reads every file base to validate it; forked pool workers inherit the cache). Never
    modified by a run: the injection works on a copy."""
    from imufdi_cli.mcapio import read_array

    return read_array(path)
