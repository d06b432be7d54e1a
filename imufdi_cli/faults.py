"""Fault models, the fault spec grammar, streaming injection and ground truth.

A fault acts on one sensor axis (``imu3.gyro.z``) or on a whole triad (``imu3.gyro``: the
IMU's present axes) from ``at`` seconds after the log start (the first IMU sample stamp,
``t0_ns``) until ``until`` seconds (exclusive), or to the end of the log. With ``o(t)`` the
nominal output and ``t_f`` the fault start, the models are:

========  ===================================================================================
step      ``o_f(t) = o(t) + amp``                                    (bias jump)
drift     ``o_f(t) = o(t) + rate * (t - t_f)``                       (ramp)
noise     ``o_f(t) = o(t) + sigma * n(t)``, ``n ~ N(0, 1)`` white; with ``factor`` the added
          ``sigma = sigma0 * sqrt(factor^2 - 1)`` so the total std is ``factor * sigma0``
stuck     ``o_f(t) = o(t_s)``, ``t_s`` the last sample before ``t_f`` (the first faulty sample
          when the fault starts with the log)
scale     ``o_f(t) = factor * o(t)`` (``ppm``: ``factor = 1 + ppm * 1e-6``)
spikes    Poisson events of ``rate`` per second, each adding ``+-amp`` (random sign) to
          ``width`` consecutive samples
========  ===================================================================================

Grammar: ``MODEL:SENSOR,key=value,...`` e.g. ``step:imu0.gyro.x,at=2.5s,amp=0.9deg/s``.
Common keys: ``at`` (default 0 s), ``until`` or ``duration`` (optional), ``id`` (optional).
TOML files hold ``[[fault]]`` tables with ``model``, ``sensor`` and the same keys.

Several faults may act on the same sensor: they are applied in list order, each on the
output of the previous ones. Random models draw from one generator per fault, seeded by
``SeedSequence(seed, spawn_key=(fault_index,))``, with a fixed number of draws per faulty
sample, so the output does not depend on how the stream is cut into blocks.
"""

from __future__ import annotations

import json
import math
import re
import sys
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import numpy as np

from imufdi_cli.array import AXES, SENSOR_TYPES, ArrayConfig, parse_sensor_id
from imufdi_cli.errors import ArrayConfigError, FaultSpecError, TruthError, UnitError
from imufdi_cli.log import ImuBlock
from imufdi_cli.units import parse_quantity, rate_dimension, sensor_dimension

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

#: Name of the MCAP metadata record describing injected faults.
METADATA_NAME: Final[str] = "imufdi.faults"
#: Topic of the ground-truth channel (one message per fault start/end).
TRUTH_TOPIC: Final[str] = "/imufdi/truth"
#: Schema name (ros2msg) of the ground-truth channel.
TRUTH_SCHEMA: Final[str] = "imufdi_msgs/msg/FaultEvent"
METADATA_FORMAT: Final[str] = "imufdi.faults/1"

_COMMON_KEYS: Final[frozenset[str]] = frozenset({"at", "until", "duration", "id"})

#: Per model: the model-specific keys a spec may carry.
MODEL_KEYS: Final[dict[str, frozenset[str]]] = {
    "step": frozenset({"amp"}),
    "drift": frozenset({"rate"}),
    "noise": frozenset({"factor", "sigma", "sigma0"}),
    "stuck": frozenset(),
    "scale": frozenset({"factor", "ppm"}),
    "spikes": frozenset({"rate", "amp", "width"}),
}
MODELS: Final[tuple[str, ...]] = tuple(sorted(MODEL_KEYS))

#: Params stored (SI) in Fault.params, per model.
_PARAM_NAMES: Final[dict[str, tuple[str, ...]]] = {
    "step": ("amp",),
    "drift": ("rate",),
    "noise": ("sigma",),
    "stuck": (),
    "scale": ("factor",),
    "spikes": ("rate", "amp", "width"),
}

_ID_PATTERN: Final = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")


def _seconds_to_ns(seconds: float) -> int:
    return round(seconds * 1e9)


@dataclass(frozen=True)
class Fault:
    """One fault, fully resolved to SI.

    Attributes
    ----------
    model : str
        One of :data:`MODELS`.
    sensors : list of str
        Full sensor ids the fault acts on (``["imu3.gyro.x", "imu3.gyro.y", ...]``); all of
        one IMU and one sensor type.
    at_s : float
        Start, seconds after the log start (first IMU sample stamp).
    until_s : float or None
        End (exclusive), seconds after the log start; None: to the end of the log.
    params : dict of str to float
        Model parameters in SI: step ``amp``; drift ``rate`` (unit/s); noise ``sigma``
        (added std) plus ``factor``/``sigma0`` when given so; scale ``factor``; spikes
        ``rate`` (1/s), ``amp``, ``width`` (samples).
    id : str
        Unique within a log (``f0``, ``f1``, ... unless the spec names one).
    spec : str
        The spec as the user wrote it (CLI grammar; TOML tables are rendered in it).
    """

    model: str
    sensors: list[str]
    at_s: float
    until_s: float | None
    params: dict[str, float] = field(default_factory=dict)
    id: str = ""
    spec: str = ""

    @property
    def imu(self) -> int:
        """IMU index the fault acts on."""
        return int(self.sensors[0].split(".")[0][3:])

    @property
    def sensor_type(self) -> str:
        """``gyro``, ``accel`` or ``mag``."""
        return self.sensors[0].split(".")[1]

    @property
    def axes(self) -> tuple[int, ...]:
        """Axis indices (0..2 for x, y, z) in the IMU frame."""
        return tuple(AXES.index(s.split(".")[2]) for s in self.sensors)

    @property
    def at_ns(self) -> int:
        """Start, integer nanoseconds after the log start."""
        return _seconds_to_ns(self.at_s)

    @property
    def until_ns(self) -> int | None:
        """End (exclusive), integer nanoseconds after the log start, or None."""
        return None if self.until_s is None else _seconds_to_ns(self.until_s)

    def active(self, t_ns: np.ndarray, t0_ns: int) -> np.ndarray:
        """Whether the fault is active at each stamp, shape (N,) bool."""
        rel = np.asarray(t_ns, dtype=np.int64) - np.int64(t0_ns)
        mask = rel >= self.at_ns
        if self.until_s is not None:
            mask &= rel < self.until_ns  # type: ignore[operator]
        return mask

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready full description (SI units)."""
        return {
            "id": self.id,
            "model": self.model,
            "sensors": list(self.sensors),
            "at_s": float(self.at_s),
            "until_s": None if self.until_s is None else float(self.until_s),
            "params": {k: float(v) for k, v in self.params.items()},
            "spec": self.spec,
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Fault:
        """Inverse of :meth:`to_dict`; raises TruthError on malformed records."""
        required = ("model", "sensors", "at_s", "params")
        try:
            missing = [k for k in required if k not in data]
            if missing:
                raise TruthError(f"fault record lacks {', '.join(missing)}: {dict(data)!r}")
            model = str(data["model"])
            if model not in MODEL_KEYS:
                raise TruthError(f"fault record: unknown model {model!r}; valid: {MODELS}")
            sensors = [str(s) for s in data["sensors"]]
            if not sensors or any(len(s.split(".")) != 3 for s in sensors):
                raise TruthError(f"fault record: bad sensors {data['sensors']!r}")
            until = data.get("until_s")
            return cls(
                model=model,
                sensors=sensors,
                at_s=float(data["at_s"]),
                until_s=None if until is None else float(until),
                params={str(k): float(v) for k, v in dict(data["params"]).items()},
                id=str(data.get("id", "")),
                spec=str(data.get("spec", "")),
            )
        except (TypeError, ValueError) as err:
            raise TruthError(f"fault record is malformed ({err}): {dict(data)!r}") from err


# --- parsing ----------------------------------------------------------------------------


def _parse_events_per_second(text: Any, name: str) -> float:
    """``"2Hz"``, ``"2"``, ``"2/s"``, ``"30/min"`` -> events per second."""
    if isinstance(text, str):
        match = re.match(r"^\s*([^/]+?)\s*/\s*([A-Za-z]+)\s*$", text)
        if match:
            count = parse_quantity(match.group(1), "dimensionless", name=name)
            return count / parse_quantity("1" + match.group(2), "time", name=name)
    return parse_quantity(text, "frequency", name=name)


def _build_fault(
    model: str,
    sensor: str,
    values: Mapping[str, Any],
    array: ArrayConfig,
    spec: str,
) -> Fault:
    """Validate one fault given as model, sensor and raw key -> value (str or number)."""
    where = f"fault {spec!r}"
    if model not in MODEL_KEYS:
        raise FaultSpecError(f"{where}: unknown model {model!r}; valid: {', '.join(MODELS)}")
    valid_keys = MODEL_KEYS[model] | _COMMON_KEYS
    for key in values:
        if key not in valid_keys:
            raise FaultSpecError(
                f"{where}: unknown key {key!r} for {model}; valid: {', '.join(sorted(valid_keys))}"
            )
    try:
        imu, sensor_type, axes = parse_sensor_id(sensor, array)
    except ArrayConfigError as err:
        raise FaultSpecError(f"{where}: sensor: {err}") from err
    sensors = [f"imu{imu}.{sensor_type}.{a}" for a in axes]
    dim = sensor_dimension(sensor_type)

    def quantity(key: str, dimension: str) -> float:
        try:
            value = parse_quantity(values[key], dimension, name=key)
        except UnitError as err:
            raise FaultSpecError(f"{where}: {err}") from err
        if not math.isfinite(value):
            raise FaultSpecError(f"{where}: {key}: {values[key]!r} is not a finite number")
        return value

    def require(*keys: str) -> None:
        if not any(k in values for k in keys):
            alternatives = " or ".join(f"{k}=" for k in keys)
            raise FaultSpecError(f"{where}: {model} needs {alternatives}")

    def exclusive(*keys: str) -> None:
        if sum(k in values for k in keys) > 1:
            raise FaultSpecError(f"{where}: give only one of {', '.join(keys)}")

    at_s = quantity("at", "time") if "at" in values else 0.0
    if at_s < 0:
        raise FaultSpecError(f"{where}: at must be >= 0 s (seconds from the log start)")
    exclusive("until", "duration")
    until_s: float | None = None
    if "until" in values:
        until_s = quantity("until", "time")
        if until_s <= at_s:
            raise FaultSpecError(
                f"{where}: until ({until_s:g} s) must be after at ({at_s:g} s): "
                "negative or zero duration"
            )
    elif "duration" in values:
        duration = quantity("duration", "time")
        if duration <= 0:
            raise FaultSpecError(f"{where}: duration must be > 0 s, got {duration:g} s")
        until_s = at_s + duration

    fault_id = ""
    if "id" in values:
        fault_id = str(values["id"])
        if not _ID_PATTERN.match(fault_id):
            raise FaultSpecError(f"{where}: id {fault_id!r} must be 1-64 of A-Z a-z 0-9 _ . -")

    params: dict[str, float] = {}
    if model == "step":
        require("amp")
        params["amp"] = quantity("amp", dim)
    elif model == "drift":
        require("rate")
        params["rate"] = quantity("rate", rate_dimension(sensor_type))
    elif model == "noise":
        require("factor", "sigma")
        exclusive("factor", "sigma")
        if "sigma" in values:
            if "sigma0" in values:
                raise FaultSpecError(f"{where}: sigma0 is only used with factor=")
            sigma = quantity("sigma", dim)
            if sigma <= 0:
                raise FaultSpecError(f"{where}: sigma (added noise std) must be > 0")
        else:
            factor = quantity("factor", "dimensionless")
            if factor < 1:
                raise FaultSpecError(
                    f"{where}: factor must be >= 1 (noise grows by adding noise), got {factor:g}"
                )
            if "sigma0" in values:
                sigma0 = quantity("sigma0", dim)
            elif sensor_type in array.noise:
                sigma0 = float(array.noise[sensor_type])
            else:
                raise FaultSpecError(
                    f"{where}: factor needs the nominal noise: give sigma0= or set "
                    f"noise.{sensor_type} in the array config (or give sigma=)"
                )
            if sigma0 <= 0:
                raise FaultSpecError(f"{where}: sigma0 must be > 0")
            sigma = sigma0 * math.sqrt(factor * factor - 1.0)
            params["factor"] = factor
            params["sigma0"] = sigma0
        params["sigma"] = sigma
    elif model == "scale":
        require("factor", "ppm")
        exclusive("factor", "ppm")
        if "factor" in values:
            params["factor"] = quantity("factor", "dimensionless")
        else:
            params["factor"] = 1.0 + quantity("ppm", "dimensionless") * 1e-6
    elif model == "spikes":
        require("rate")
        require("amp")
        try:
            rate = _parse_events_per_second(values["rate"], "rate")
        except UnitError as err:
            raise FaultSpecError(f"{where}: {err} (events per second, e.g. 2Hz, 0.5/s)") from err
        if rate <= 0:
            raise FaultSpecError(f"{where}: rate (events per second) must be > 0")
        params["rate"] = rate
        params["amp"] = quantity("amp", dim)
        width = 1.0
        if "width" in values:
            width = quantity("width", "dimensionless")
            if width < 1 or width != int(width):
                raise FaultSpecError(
                    f"{where}: width must be a whole number of samples >= 1, got {width:g}"
                )
        params["width"] = float(width)
    return Fault(
        model=model,
        sensors=sensors,
        at_s=at_s,
        until_s=until_s,
        params=params,
        id=fault_id,
        spec=spec,
    )


def parse_fault_spec(text: str, array: ArrayConfig) -> Fault:
    """Parse ``MODEL:SENSOR,key=value,...`` against an array.

    Parameters
    ----------
    text : str
        e.g. ``"step:imu0.gyro.x,at=2.5s,amp=0.9deg/s"``,
        ``"drift:imu1.accel.z,at=3s,until=8s,rate=0.01g/s"``,
        ``"noise:imu0.accel.x,at=12s,until=18s,factor=3"``.
    array : ArrayConfig
        The array the fault is injected into (sensor ids, nominal noise).

    Returns
    -------
    Fault
        With ``id`` empty unless the spec sets ``id=`` (the injector numbers the others).

    Raises
    ------
    FaultSpecError
        Unknown model/key/sensor, IMU past the array, bad or missing value, wrong units,
        ``until <= at``. The message names the field and the valid choices.
    """
    spec = str(text).strip()
    head, sep, rest = spec.partition(":")
    model = head.strip().lower()
    if not sep or not model:
        raise FaultSpecError(
            f"fault {spec!r}: expected MODEL:SENSOR,key=value,... "
            f"(e.g. step:imu0.gyro.x,at=2.5s,amp=0.9deg/s); models: {', '.join(MODELS)}"
        )
    if model not in MODEL_KEYS:
        raise FaultSpecError(f"fault {spec!r}: unknown model {model!r}; valid: {', '.join(MODELS)}")
    items = [item.strip() for item in rest.split(",")]
    sensor = items[0]
    if not sensor:
        raise FaultSpecError(f"fault {spec!r}: missing sensor after {model}: (e.g. imu0.gyro.x)")
    values: dict[str, str] = {}
    for item in items[1:]:
        key, eq, value = item.partition("=")
        key = key.strip()
        if not eq or not key or not value.strip():
            raise FaultSpecError(f"fault {spec!r}: {item!r} is not key=value")
        if key in values:
            raise FaultSpecError(f"fault {spec!r}: key {key!r} given twice")
        values[key] = value.strip()
    return _build_fault(model, sensor, values, array, spec)


def fault_from_table(table: Mapping[str, Any], array: ArrayConfig, *, where: str) -> Fault:
    """Build a fault from a TOML ``[[fault]]`` table (``model``, ``sensor`` and keys)."""
    if not isinstance(table, Mapping):
        raise FaultSpecError(f"{where}: expected a table with model, sensor and parameters")
    missing = [k for k in ("model", "sensor") if k not in table]
    if missing:
        raise FaultSpecError(f"{where}: missing {' and '.join(missing)}")
    model = str(table["model"]).strip().lower()
    sensor = str(table["sensor"]).strip()
    values: dict[str, Any] = {}
    for key, value in table.items():
        if key in ("model", "sensor"):
            continue
        if isinstance(value, bool) or not isinstance(value, (str, int, float)):
            raise FaultSpecError(f"{where}: {key} must be a string or a number, got {value!r}")
        values[str(key)] = value
    spec = ",".join([f"{model}:{sensor}", *(f"{k}={v}" for k, v in values.items())])
    try:
        return _build_fault(model, sensor, values, array, spec)
    except FaultSpecError as err:
        raise FaultSpecError(f"{where}: {err}") from err


def load_fault_file(path: str | Path, array: ArrayConfig) -> list[Fault]:
    """Load ``[[fault]]`` tables from a TOML file.

    Example file::

        [[fault]]
        model = "step"
        sensor = "imu0.gyro.x"
        at = "2.5s"
        amp = "0.9deg/s"
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        reason = getattr(err, "strerror", None) or str(err)
        raise FaultSpecError(f"cannot read fault file {path}: {reason}") from err
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise FaultSpecError(f"{path}: not valid TOML ({err})") from err
    except RecursionError as err:  # tomllib parses nested arrays/tables recursively
        raise FaultSpecError(
            f"{path}: not valid TOML (arrays or tables nested too deeply)"
        ) from err
    for key in data:
        if key != "fault":
            raise FaultSpecError(f"{path}: unknown top-level key {key!r}; valid: fault")
    tables = data.get("fault", [])
    if not isinstance(tables, list) or not tables:
        raise FaultSpecError(f"{path}: needs at least one [[fault]] table")
    return [
        fault_from_table(table, array, where=f"{path}: fault[{i}]")
        for i, table in enumerate(tables)
    ]


def validate_faults(
    faults: Sequence[Fault],
    array: ArrayConfig,
    *,
    log_duration_s: float | None = None,
    taken_ids: Iterable[str] = (),
) -> None:
    """Check faults against the array and, when known, the log duration; ids unique.

    Raises FaultSpecError naming the fault and field.
    """
    seen = set(taken_ids)
    for fault in faults:
        where = f"fault {fault.spec or fault.id!r}"
        for sensor in fault.sensors:
            try:
                parse_sensor_id(sensor, array)
            except ArrayConfigError as err:
                raise FaultSpecError(f"{where}: sensor: {err}") from err
        if log_duration_s is not None and fault.at_s > log_duration_s:
            raise FaultSpecError(
                f"{where}: at ({fault.at_s:g} s) is after the log ends ({log_duration_s:g} s)"
            )
        if fault.id:
            if fault.id in seen:
                raise FaultSpecError(f"{where}: id {fault.id!r} is already used in this log")
            seen.add(fault.id)


# --- ground truth -----------------------------------------------------------------------


def active_mask(
    faults: Sequence[Fault], sensor_ids: Sequence[str], t_ns: np.ndarray, t0_ns: int
) -> np.ndarray:
    """Ground truth: which sensors are faulty at which samples.

    Parameters
    ----------
    faults : sequence of Fault
    sensor_ids : sequence of str
        Columns, e.g. ``array.sensor_ids("gyro")``.
    t_ns : ndarray, shape (N,), int64
        Sample stamps, ns.
    t0_ns : int
        Log start (first IMU sample stamp), ns.

    Returns
    -------
    ndarray, shape (N, n), bool
        ``[i, j]`` true when a fault acting on ``sensor_ids[j]`` is active at ``t_ns[i]``
        (``at <= t - t0 < until``). Spikes faults count as active over their whole window.
    """
    t_ns = np.asarray(t_ns, dtype=np.int64)
    mask = np.zeros((t_ns.shape[0], len(sensor_ids)), dtype=bool)
    column = {sensor: j for j, sensor in enumerate(sensor_ids)}
    for fault in faults:
        columns = [column[s] for s in fault.sensors if s in column]
        if columns:
            mask[:, columns] |= fault.active(t_ns, t0_ns)[:, None]
    return mask


def faults_from_metadata(meta: Mapping[str, str]) -> list[Fault]:
    """All faults recorded in an ``imufdi.faults`` metadata record (earlier runs first)."""
    if "json" not in meta:
        raise TruthError(f"{METADATA_NAME} metadata has no 'json' entry")
    record = _load_record(meta["json"])
    faults: list[Fault] = []
    for run in [*record.get("previous", []), record]:
        faults += [Fault.from_dict(item) for item in run.get("faults", [])]
    return faults


def _load_record(text: str) -> dict[str, Any]:
    try:
        record = json.loads(text)
    except (TypeError, ValueError) as err:
        raise TruthError(f"{METADATA_NAME} metadata is not valid JSON ({err})") from err
    if not isinstance(record, dict) or not isinstance(record.get("faults"), list):
        raise TruthError(f"{METADATA_NAME} metadata lacks a 'faults' list")
    if not isinstance(record.get("previous", []), list):
        raise TruthError(f"{METADATA_NAME} metadata: 'previous' must be a list")
    return record


# --- injection --------------------------------------------------------------------------


@dataclass
class _FaultState:
    """Streaming state of one fault on its (imu, sensor type) stream."""

    fault: Fault
    axes: np.ndarray  # (k,) axis indices
    rng: np.random.Generator
    at_ns: int
    until_ns: int | None
    stuck_value: np.ndarray | None = None  # (k,)
    last_t_ns: int | None = None  # previous sample stamp (spikes: Poisson step)
    active_count: int = 0  # faulty samples seen so far
    last_event: np.ndarray | None = None  # (k,) active index of the last spike start
    last_sign: np.ndarray | None = None  # (k,) sign of the last spike


class FaultInjector:
    """Apply faults to a stream of IMU samples, deterministically given ``seed``.

    Parameters
    ----------
    faults : list of Fault
        Faults of this run, in application order. Faults without an id are numbered
        ``f<k>`` after any previous faults.
    array : ArrayConfig
    seed : int
        Seed of the random models (noise, spikes).
    t0_ns : int
        Log start (first IMU sample stamp), ns; ``at``/``until`` count from it.
    log_duration_s : float, optional
        When known, faults starting after the log ends are rejected.
    previous_metadata : dict, optional
        An ``imufdi.faults`` record already in the log; kept in :meth:`metadata`.
    """

    def __init__(
        self,
        faults: list[Fault],
        array: ArrayConfig,
        *,
        seed: int,
        t0_ns: int,
        log_duration_s: float | None = None,
        previous_metadata: Mapping[str, str] | None = None,
    ) -> None:
        if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or seed < 0:
            raise FaultSpecError(f"seed must be a non-negative integer, got {seed!r}")
        self.array = array
        self.seed = int(seed)
        self.t0_ns = int(t0_ns)
        self.previous_runs: list[dict[str, Any]] = []
        if previous_metadata is not None:
            record = _load_record(previous_metadata["json"]) if previous_metadata else None
            if record is not None:
                self.previous_runs = [*record.pop("previous", []), record]
        previous_faults = [
            Fault.from_dict(item) for run in self.previous_runs for item in run["faults"]
        ]
        taken = {f.id for f in previous_faults if f.id}
        validate_faults(faults, array, log_duration_s=log_duration_s, taken_ids=taken)
        taken |= {f.id for f in faults if f.id}
        numbered: list[Fault] = []
        counter = len(previous_faults)
        for fault in faults:
            if not fault.id:
                while f"f{counter}" in taken:
                    counter += 1
                fault = Fault(**{**fault.__dict__, "id": f"f{counter}"})
                taken.add(fault.id)
                counter += 1
            numbered.append(fault)
        self.faults: list[Fault] = numbered
        self._streams: dict[tuple[int, str], list[_FaultState]] = {}
        for index, fault in enumerate(numbered):
            state = _FaultState(
                fault=fault,
                axes=np.asarray(fault.axes, dtype=np.intp),
                rng=np.random.default_rng(np.random.SeedSequence(self.seed, spawn_key=(index,))),
                at_ns=fault.at_ns,
                until_ns=fault.until_ns,
            )
            self._streams.setdefault((fault.imu, fault.sensor_type), []).append(state)

    def affects(self, imu: int, sensor_type: str) -> bool:
        """Whether any fault acts on this IMU's sensor type."""
        return (int(imu), sensor_type) in self._streams

    def apply(self, imu: int, sensor_type: str, t_ns: np.ndarray, values: np.ndarray) -> np.ndarray:
        """Faulted copy of one IMU's triads of one sensor type.

        Parameters
        ----------
        imu : int
        sensor_type : str
        t_ns : ndarray, shape (N,), int64
            Stamps, ns, increasing; consecutive calls per (imu, sensor_type) continue in time.
        values : ndarray, shape (N, 3)
            Measurements in the IMU frame, SI.

        Returns
        -------
        ndarray, shape (N, 3), float64
            New array (the input is not modified).
        """
        out = np.array(values, dtype=np.float64, copy=True)
        if out.ndim != 2 or out.shape[1] != 3:
            raise ValueError(f"values must have shape (N, 3), got {out.shape}")
        t_ns = np.asarray(t_ns, dtype=np.int64)
        if t_ns.shape != (out.shape[0],):
            raise ValueError(f"t_ns must have shape ({out.shape[0]},), got {t_ns.shape}")
        states = self._streams.get((int(imu), sensor_type))
        if not states or out.shape[0] == 0:
            if states and t_ns.size:
                for state in states:
                    state.last_t_ns = int(t_ns[-1])
            return out
        rel = t_ns - np.int64(self.t0_ns)
        for state in states:
            self._apply_one(state, t_ns, rel, out)
        return out

    def _apply_one(
        self, state: _FaultState, t_ns: np.ndarray, rel: np.ndarray, out: np.ndarray
    ) -> None:
        fault = state.fault
        axes = state.axes
        before = rel < state.at_ns
        active = ~before
        if state.until_ns is not None:
            active &= rel < state.until_ns
        n_active = int(np.count_nonzero(active))
        if fault.model == "stuck":
            if np.any(before):
                last_before = np.flatnonzero(before)[-1]
                state.stuck_value = out[last_before, axes].copy()
            if n_active and state.stuck_value is None:
                state.stuck_value = out[np.flatnonzero(active)[0], axes].copy()
        previous_t = state.last_t_ns
        state.last_t_ns = int(t_ns[-1])
        if n_active == 0:
            return
        rows = np.flatnonzero(active)
        block = out[np.ix_(rows, axes)]
        params = fault.params
        if fault.model == "step":
            block += params["amp"]
        elif fault.model == "drift":
            elapsed_s = (rel[rows] - np.int64(state.at_ns)).astype(np.float64) * 1e-9
            block += params["rate"] * elapsed_s[:, None]
        elif fault.model == "noise":
            block += params["sigma"] * state.rng.standard_normal((n_active, axes.size))
        elif fault.model == "stuck":
            assert state.stuck_value is not None
            block[:] = state.stuck_value
        elif fault.model == "scale":
            with np.errstate(over="ignore"):  # a huge input value becomes inf: flagged later
                block *= params["factor"]
        elif fault.model == "spikes":
            block += self._spikes(state, t_ns, rows, previous_t)
        out[np.ix_(rows, axes)] = block
        state.active_count += n_active

    def _spikes(
        self, state: _FaultState, t_ns: np.ndarray, rows: np.ndarray, previous_t: int | None
    ) -> np.ndarray:
        """Spike offsets for the faulty rows, shape (n_active, k); updates burst state."""
        params = state.fault.params
        n_active, k = rows.size, state.axes.size
        # time since the previous sample of the stream: Poisson event probability per sample
        stamps = t_ns.astype(np.float64)
        dt = np.empty(t_ns.size)
        dt[1:] = np.diff(stamps) * 1e-9
        dt[0] = (
            (t_ns[0] - previous_t) * 1e-9
            if previous_t is not None
            else 1.0 / float(self.array.rate_hz)
        )
        probability = -np.expm1(-params["rate"] * np.clip(dt[rows], 0.0, None))
        draws = state.rng.random((n_active, k, 2))  # fixed: 2 uniforms per sample and axis
        events = draws[:, :, 0] < probability[:, None]
        signs = np.where(draws[:, :, 1] < 0.5, -1.0, 1.0)
        if state.last_event is None or state.last_sign is None:
            state.last_event = np.full(k, -(2**62), dtype=np.int64)
            state.last_sign = np.ones(k)
        local = np.arange(n_active)
        position = np.maximum.accumulate(np.where(events, local[:, None], -1), axis=0)
        has_event = position >= 0
        safe = np.clip(position, 0, None)
        event_index = np.where(has_event, state.active_count + safe, state.last_event[None, :])
        sign = np.where(
            has_event, np.take_along_axis(signs, safe, axis=0), state.last_sign[None, :]
        )
        global_index = state.active_count + local[:, None]
        in_burst = (global_index - event_index) < int(params["width"])
        state.last_event = event_index[-1].astype(np.int64)
        state.last_sign = sign[-1].copy()
        return np.where(in_burst, params["amp"] * sign, 0.0)

    def apply_block(self, block: ImuBlock) -> ImuBlock:
        """Faulted copy of an aligned block (all IMUs, all sensor types present)."""
        fields: dict[str, np.ndarray | None] = {}
        for sensor_type in SENSOR_TYPES:
            triads = block.get(sensor_type)
            if triads is None:
                fields[sensor_type] = None
                continue
            result = np.array(triads, dtype=np.float64, copy=True)
            for imu, stream_type in self._streams:
                if stream_type == sensor_type and imu < result.shape[1]:
                    result[:, imu, :] = self.apply(imu, sensor_type, block.t_ns, triads[:, imu, :])
            fields[sensor_type] = result
        return ImuBlock(t_ns=block.t_ns.copy(), **fields)

    def truth_events(self) -> list[dict[str, Any]]:
        """Start/end events of this run's faults, in time order.

        Each is ``{"event": "start"|"end", "t_ns": int, "t_s": float, "fault_id": str,
        "fault": Fault.to_dict()}``; faults lasting to the end of the log have no end event.
        """
        events: list[dict[str, Any]] = []
        for fault in self.faults:
            marks = [("start", fault.at_ns)]
            if fault.until_ns is not None:
                marks.append(("end", fault.until_ns))
            for name, offset in marks:
                events.append(
                    {
                        "event": name,
                        "t_ns": self.t0_ns + offset,
                        "t_s": offset * 1e-9,
                        "fault_id": fault.id,
                        "fault": fault.to_dict(),
                    }
                )
        events.sort(key=lambda e: (e["t_ns"], e["event"] != "end"))
        return events

    def metadata(self) -> dict[str, str]:
        """The ``imufdi.faults`` metadata record: ``{"json": ...}``.

        The JSON holds ``format``, ``seed``, ``t0_ns``, ``faults`` (this run, SI) and
        ``previous`` (earlier injection runs on the same log, oldest first).
        """
        record = {
            "format": METADATA_FORMAT,
            "seed": self.seed,
            "t0_ns": self.t0_ns,
            "faults": [fault.to_dict() for fault in self.faults],
            "previous": self.previous_runs,
        }
        return {"json": json.dumps(record, separators=(",", ":"), sort_keys=True)}

    def all_faults(self) -> list[Fault]:
        """Previous runs' faults followed by this run's."""
        return faults_from_metadata(self.metadata())


# --- file level: imufdi inject -------------------------------------------------------------


@dataclass
class InjectResult:
    """What :func:`inject_file` did.

    Attributes
    ----------
    output : str
        Path written (``"-"`` for stdout).
    seed : int
    faults : list of Fault
        Faults injected by this run (with their ids).
    previous_faults : list of Fault
        Faults already recorded in the input.
    t0_ns : int
        Log start (first IMU sample stamp), ns.
    duration_s : float
        Last minus first IMU sample stamp, s.
    imu_topics : list of str
        IMU topics in IMU index order.
    warnings : list of str
        Reader warnings (e.g. log time used for Imu messages without header stamps).
    messages : int
        Messages copied (all channels, input only).
    messages_patched : int
        IMU/magnetometer messages whose values were rewritten.
    truth_messages : int
        Messages added to ``/imufdi/truth``.
    warnings : list of str
        Problems the reader met in the input (e.g. a corrupt chunk skipped: its messages
        are not in the output).
    """

    output: str
    seed: int
    faults: list[Fault]
    previous_faults: list[Fault]
    t0_ns: int
    duration_s: float
    imu_topics: list[str]
    messages: int = 0
    messages_patched: int = 0
    truth_messages: int = 0
    warnings: list[str] = field(default_factory=list)


def _same_file(a: str, b: str) -> bool:
    try:
        return Path(a).resolve() == Path(b).resolve()
    except OSError:
        return False


def inject_file(
    source: str | Path,
    output: str | Path,
    faults_specs: Sequence[str],
    fault_files: Sequence[str | Path],
    *,
    seed: int,
    compression: str = "zstd",
    topics: Sequence[str] | None = None,
    time_source: str = "auto",
    progress: Any = None,
) -> InjectResult:
    """Copy an MCAP log with faults injected into its IMU messages, plus ground truth.

    Every channel, message and metadata record of the input is copied; IMU (and
    magnetometer) messages of faulted sensors are patched in place (all other bytes
    identical). Adds the ``/imufdi/truth`` channel (``imufdi_msgs/msg/FaultEvent``, CDR, one
    message per fault start/end; the JSON truth and alarm events of an older imufdi are
    re-encoded as FaultEvent / FdiEvent)
    and the ``imufdi.faults`` metadata record (seed, faults in SI, earlier runs under
    ``previous``). All specs are validated against the array and the log duration before
    anything is written; on failure no output file is left.

    Parameters
    ----------
    source : str or Path
        Input MCAP, or ``"-"`` for stdin (buffered in memory: the log is read twice).
    output : str or Path
        Output MCAP, or ``"-"`` for stdout. Must not be the input.
    faults_specs : sequence of str
        Specs in the ``MODEL:SENSOR,key=value,...`` grammar.
    fault_files : sequence of path
        TOML files of ``[[fault]]`` tables.
    seed : int
        Seed of the random fault models.
    compression : {"zstd", "lz4", "none"}
        Chunk compression of the output.
    topics : sequence of str, optional
        Imu topics in IMU order (``/topic:field`` for an Imu inside a larger message), as
        :class:`~imufdi_cli.mcapio.ImuArrayReader` takes them; default all.
    time_source : {"auto", "header", "log_time"}
        Stamps the fault times refer to (see :class:`~imufdi_cli.mcapio.ImuArrayReader`).
    progress : callable, optional
        ``progress(done, total)`` in seconds of log time, both passes counted
        (:mod:`imufdi_cli.progress`).

    Raises
    ------
    FaultSpecError
        No fault given, or a bad spec (exit code 2).
    McapInputError
        Unreadable input or no IMU channel (exit code 3).
    """
    import io

    from imufdi_cli import mcapio
    from imufdi_cli.errors import McapInputError, UsageError
    from imufdi_cli.mcapio.events import (
        decode_events,
        encode_fault_events,
        encode_fdi_event_dicts,
        is_event_channel,
        register_events_channel,
        register_truth_channel,
    )
    from imufdi_cli.progress import LogTimeProgress

    if not faults_specs and not fault_files:
        raise FaultSpecError("inject needs at least one --fault SPEC or --faults FILE")
    source_name, output_name = str(source), str(output)
    if output_name != "-" and source_name != "-" and _same_file(source_name, output_name):
        raise UsageError(f"output {output_name} is the input file; inputs are never modified")

    buffered: io.BytesIO | None = None
    if source_name == "-":
        buffered = io.BytesIO(sys.stdin.buffer.read())

    def open_input() -> Any:
        if buffered is not None:
            buffered.seek(0)
            return buffered
        return source_name

    # The array and the topic -> IMU index rule, exactly as the reader sees them.
    with mcapio.ImuArrayReader(
        open_input(), topics=topics, time_source=time_source
    ) as array_reader:
        array = array_reader.array
        imu_topics = list(array_reader.imu_topics)
        imu_fields = dict(array_reader.imu_fields)
        use_log_time = array_reader.time_source == "log_time"
        reader_warnings = list(array_reader.warnings)
        mag_topics = list(array_reader.mag_topics) if array.has("mag") else []
    imu_index = {topic: k for k, topic in enumerate(imu_topics)}
    mag_index = {topic: k for k, topic in enumerate(mag_topics)}

    # Pass 1: channels, metadata, the IMU time span (and truth on older JSON channels).
    first_ns: int | None = None
    last_ns: int | None = None
    legacy_truth: list[dict[str, Any]] = []
    legacy_alarms: list[tuple[int, dict[str, Any]]] = []
    with mcapio.McapSource(open_input()) as reader:
        tracker = LogTimeProgress(progress, reader.summary_time_range, passes=2)
        for batch in reader.batches():
            tracker.batch(batch)
            for cid in np.unique(batch.channel_id).tolist():
                channel = reader.channels[cid]
                if channel.message_encoding == "json" and is_event_channel(channel):
                    sub = batch.select(batch.channel_id == cid)
                    if channel.topic == TRUTH_TOPIC:
                        legacy_truth += decode_events(sub, channel)
                    else:
                        legacy_alarms += zip(sub.log_time.tolist(), decode_events(sub, channel))
            # one bulk decode per schema: channels sharing a schema share a codec
            groups: dict[tuple[Any, str, str], list[int]] = {}
            for cid in np.unique(batch.channel_id).tolist():
                channel = reader.channels[cid]
                if _is_imu_source(channel, imu_fields):
                    key = (channel.schema, channel.message_encoding, imu_fields[channel.topic])
                    groups.setdefault(key, []).append(cid)
            for (_, _, imu_path), cids in groups.items():
                part = batch.select(np.flatnonzero(np.isin(batch.channel_id, cids)))
                decoded = mcapio.decode_imu(part, reader.channels[cids[0]], imu_path)
                stamps = decoded.log_time if use_log_time else decoded.t_ns
                if stamps.size:
                    low, high = int(stamps.min()), int(stamps.max())
                    first_ns = low if first_ns is None else min(first_ns, low)
                    last_ns = high if last_ns is None else max(last_ns, high)
        channels = dict(reader.channels)
        metadata = {name: dict(values) for name, values in reader.metadata.items()}
    if first_ns is None or last_ns is None:
        raise McapInputError(f"{source_name}: no sensor_msgs/msg/Imu messages to inject into")
    imu_channels = {
        cid: imu_index[ch.topic] for cid, ch in channels.items() if _is_imu_source(ch, imu_fields)
    }
    mag_channels = {
        cid: mag_index[ch.topic]
        for cid, ch in channels.items()
        if ch.topic in mag_index and mcapio.is_mag_channel(ch)
    }
    array_recorded = "imufdi.array" in metadata

    # Validate every spec before writing anything.
    faults = [parse_fault_spec(spec, array) for spec in faults_specs]
    for path in fault_files:
        faults += load_fault_file(path, array)
    duration_s = (last_ns - first_ns) * 1e-9
    injector = FaultInjector(
        faults,
        array,
        seed=seed,
        t0_ns=first_ns,
        log_duration_s=duration_s,
        previous_metadata=metadata.get(METADATA_NAME),
    )
    # Every faulted stream must exist in the log and be patchable (CDR) before writing.
    streams = {(k, t): cid for cid, k in imu_channels.items() for t in ("gyro", "accel")}
    streams.update({(k, "mag"): cid for cid, k in mag_channels.items()})
    for fault in injector.faults:
        cid = streams.get((fault.imu, fault.sensor_type))
        if cid is None:
            raise FaultSpecError(
                f"fault {fault.spec!r}: the log has no {fault.sensor_type} topic for "
                f"imu{fault.imu}; IMU topics: {', '.join(imu_topics)}"
            )
        if channels[cid].message_encoding != "cdr":
            raise McapInputError(
                f"fault {fault.spec!r}: {channels[cid].topic} is "
                f"{channels[cid].message_encoding!r}-encoded; only CDR messages can be patched"
            )
    previous_faults = [
        Fault.from_dict(item) for run in injector.previous_runs for item in run["faults"]
    ]
    result = InjectResult(
        output=output_name,
        seed=injector.seed,
        faults=injector.faults,
        previous_faults=previous_faults,
        t0_ns=first_ns,
        duration_s=duration_s,
        imu_topics=imu_topics,
        warnings=reader_warnings,
    )

    # Pass 2: copy, patching the faulted IMU messages.
    with (
        mcapio.McapSource(open_input()) as reader,
        mcapio.McapWriter(output, compression=compression) as writer,
    ):
        # JSON event channels of an older imufdi are re-encoded as FaultEvent / FdiEvent
        legacy_ids = [
            cid
            for cid, ch in channels.items()
            if ch.message_encoding == "json" and is_event_channel(ch)
        ]
        writer.copy_channels({c: ch for c, ch in channels.items() if c not in legacy_ids})
        for name, values in metadata.items():
            if name != METADATA_NAME:
                writer.add_metadata(name, values)
        if not array_recorded:
            writer.add_metadata("imufdi.array", {"json": array.to_json()})
        writer.add_metadata(METADATA_NAME, injector.metadata())
        truth_ids = [
            cid
            for cid, ch in channels.items()
            if ch.topic == TRUTH_TOPIC and ch.message_encoding == "cdr" and is_event_channel(ch)
        ]
        truth_channel = truth_ids[0] if truth_ids else register_truth_channel(writer)
        events = legacy_truth + injector.truth_events()
        writer.add_batch(encode_fault_events(truth_channel, events))
        result.truth_messages += len(events) - len(legacy_truth)
        if legacy_alarms:
            writer.add_batch(
                encode_fdi_event_dicts(
                    register_events_channel(writer),
                    [t for t, _ in legacy_alarms],
                    [e for _, e in legacy_alarms],
                )
            )
        tracker.next_pass()
        for batch in reader.batches():
            tracker.batch(batch)
            if legacy_ids:
                batch = batch.select(~np.isin(batch.channel_id, legacy_ids))
            result.messages += len(batch)
            patched, count = _patch_batch(
                batch,
                channels,
                imu_channels,
                mag_channels,
                injector,
                imu_fields=imu_fields,
                use_log_time=use_log_time,
            )
            result.messages_patched += count
            writer.add_batch(patched)
        result.warnings = list(reader.warnings)
    return result


def _is_imu_source(channel: Any, imu_fields: Mapping[str, str]) -> bool:
    """The channel carries the Imu of one of the array's topics (at that topic's field)."""
    from imufdi_cli.mcapio.imu import imu_fields_of

    path = imu_fields.get(channel.topic)
    return path is not None and path in imu_fields_of(channel)


def _patch_batch(
    batch: Any,
    channels: Mapping[int, Any],
    imu_channels: Mapping[int, int],
    mag_channels: Mapping[int, int],
    injector: FaultInjector,
    *,
    imu_fields: Mapping[str, str] | None = None,
    use_log_time: bool = False,
) -> tuple[Any, int]:
    """The batch with faulted IMU/magnetometer messages rewritten, in the original order.

    ``imu_fields``: topic -> path of the Imu inside its messages; ``use_log_time``: fault
    times refer to the log time instead of the header stamps."""
    from imufdi_cli import mcapio

    pieces: list[Any] = []
    positions: list[np.ndarray] = []
    patched = 0
    for cid in np.unique(batch.channel_id):
        channel_id = int(cid)
        imu = imu_channels.get(channel_id, mag_channels.get(channel_id))
        if imu is None:
            continue
        is_mag = channel_id in mag_channels
        types = ("mag",) if is_mag else ("gyro", "accel")
        if not any(injector.affects(imu, t) for t in types):
            continue
        where = np.flatnonzero(batch.channel_id == cid)
        part = batch.select(where)
        channel = channels[channel_id]
        path = "" if is_mag else (imu_fields or {}).get(channel.topic, "")
        if is_mag:
            fields = mcapio.decode_mag(part, channel)
        else:
            fields = mcapio.decode_imu(part, channel, path)
        stamps = fields.log_time if use_log_time else fields.t_ns
        new_values: dict[str, np.ndarray] = {}
        for sensor_type in types:
            decoded = getattr(fields, sensor_type)
            if decoded is None or not injector.affects(imu, sensor_type):
                continue
            new_values[sensor_type] = injector.apply(imu, sensor_type, stamps, decoded)
        if not new_values:
            continue
        if is_mag:
            pieces.append(mcapio.patch_mag(part, channel, mag=new_values["mag"]))
        else:
            pieces.append(mcapio.patch_imu(part, channel, field=path, **new_values))
        positions.append(where)
        patched += len(where)
    if not pieces:
        return batch, 0
    untouched = np.ones(len(batch), dtype=bool)
    for where in positions:
        untouched[where] = False
    rest = np.flatnonzero(untouched)
    if rest.size:
        pieces.append(batch.select(rest))
        positions.append(rest)
    joined = mcapio.MessageBatch.concatenate(pieces)
    order = np.argsort(np.concatenate(positions), kind="stable")
    return joined.select(order), patched
