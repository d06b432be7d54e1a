"""The fault spec grammar (``MODEL:SENSOR,key=value,...``) and TOML ``[[fault]]`` files
(part of :mod:`imufdi_cli.faults`).
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

from imufdi_cli.array import ArrayConfig, parse_sensor_id
from imufdi_cli.errors import ArrayConfigError, FaultSpecError, UnitError
from imufdi_cli.faults.models import MODEL_KEYS, MODELS, Fault
from imufdi_cli.tomlfile import parse_toml
from imufdi_cli.units import parse_quantity, rate_dimension, sensor_dimension

_COMMON_KEYS: Final[frozenset[str]] = frozenset({"at", "until", "duration", "id"})

_ID_PATTERN: Final = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")


# --- parsing ----------------------------------------------------------------------------


def _parse_events_per_second(text: Any, name: str) -> float:
    """``"2Hz"``, ``"2"``, ``"2/s"``, ``"30/min"`` -> events per second."""
    if isinstance(text, str):
        match = re.match(r"^\s*([^/]+?)\s*/\s*([A-Za-z]+)\s*$", text)
        if match:
            count = parse_quantity(match.group(1), "dimensionless", name=name)
            return count / parse_quantity("1" + match.group(2), "time", name=name)
    return parse_quantity(text, "frequency", name=name)


@dataclass(frozen=True)
class _RawSpec:
    """One fault's raw key -> value (str or number) while it is being checked."""

    model: str
    values: Mapping[str, Any]
    where: str  # ``fault 'SPEC'``: the prefix of every message

    def error(self, message: str) -> FaultSpecError:
        return FaultSpecError(f"{self.where}: {message}")

    def quantity(self, key: str, dimension: str) -> float:
        """``values[key]`` in SI, finite."""
        try:
            value = parse_quantity(self.values[key], dimension, name=key)
        except UnitError as err:
            raise self.error(str(err)) from err
        if not math.isfinite(value):
            raise self.error(f"{key}: {self.values[key]!r} is not a finite number")
        return value

    def require(self, *keys: str) -> None:
        if not any(k in self.values for k in keys):
            alternatives = " or ".join(f"{k}=" for k in keys)
            raise self.error(f"{self.model} needs {alternatives}")

    def exclusive(self, *keys: str) -> None:
        if sum(k in self.values for k in keys) > 1:
            raise self.error(f"give only one of {', '.join(keys)}")


def _window(raw: _RawSpec) -> tuple[float, float | None]:
    """``at`` and ``until`` (or ``at + duration``), seconds from the log start."""
    at_s = raw.quantity("at", "time") if "at" in raw.values else 0.0
    if at_s < 0:
        raise raw.error("at must be >= 0 s (seconds from the log start)")
    raw.exclusive("until", "duration")
    if "until" in raw.values:
        until_s = raw.quantity("until", "time")
        if until_s <= at_s:
            raise raw.error(
                f"until ({until_s:g} s) must be after at ({at_s:g} s): negative or zero duration"
            )
        return at_s, until_s
    if "duration" in raw.values:
        duration = raw.quantity("duration", "time")
        if duration <= 0:
            raise raw.error(f"duration must be > 0 s, got {duration:g} s")
        return at_s, at_s + duration
    return at_s, None


def _fault_id(raw: _RawSpec) -> str:
    if "id" not in raw.values:
        return ""
    fault_id = str(raw.values["id"])
    if not _ID_PATTERN.match(fault_id):
        raise raw.error(f"id {fault_id!r} must be 1-64 of A-Z a-z 0-9 _ . -")
    return fault_id


def _step_params(raw: _RawSpec, sensor_type: str, array: ArrayConfig) -> dict[str, float]:
    raw.require("amp")
    return {"amp": raw.quantity("amp", sensor_dimension(sensor_type))}


def _drift_params(raw: _RawSpec, sensor_type: str, array: ArrayConfig) -> dict[str, float]:
    raw.require("rate")
    return {"rate": raw.quantity("rate", rate_dimension(sensor_type))}


def _noise_params(raw: _RawSpec, sensor_type: str, array: ArrayConfig) -> dict[str, float]:
    """``sigma`` (added std) directly, or from ``factor`` and the nominal ``sigma0``."""
    dim = sensor_dimension(sensor_type)
    raw.require("factor", "sigma")
    raw.exclusive("factor", "sigma")
    if "sigma" in raw.values:
        if "sigma0" in raw.values:
            raise raw.error("sigma0 is only used with factor=")
        sigma = raw.quantity("sigma", dim)
        if sigma <= 0:
            raise raw.error("sigma (added noise std) must be > 0")
        return {"sigma": sigma}
    factor = raw.quantity("factor", "dimensionless")
    if factor < 1:
        raise raw.error(f"factor must be >= 1 (noise grows by adding noise), got {factor:g}")
    if "sigma0" in raw.values:
        sigma0 = raw.quantity("sigma0", dim)
    elif sensor_type in array.noise:
        sigma0 = float(array.noise[sensor_type])
    else:
        raise raw.error(
            f"factor needs the nominal noise: give sigma0= or set "
            f"noise.{sensor_type} in the array config (or give sigma=)"
        )
    if sigma0 <= 0:
        raise raw.error("sigma0 must be > 0")
    return {"factor": factor, "sigma0": sigma0, "sigma": sigma0 * math.sqrt(factor * factor - 1.0)}


def _stuck_params(raw: _RawSpec, sensor_type: str, array: ArrayConfig) -> dict[str, float]:
    return {}


def _scale_params(raw: _RawSpec, sensor_type: str, array: ArrayConfig) -> dict[str, float]:
    raw.require("factor", "ppm")
    raw.exclusive("factor", "ppm")
    if "factor" in raw.values:
        return {"factor": raw.quantity("factor", "dimensionless")}
    return {"factor": 1.0 + raw.quantity("ppm", "dimensionless") * 1e-6}


def _spikes_params(raw: _RawSpec, sensor_type: str, array: ArrayConfig) -> dict[str, float]:
    raw.require("rate")
    raw.require("amp")
    try:
        rate = _parse_events_per_second(raw.values["rate"], "rate")
    except UnitError as err:
        raise raw.error(f"{err} (events per second, e.g. 2Hz, 0.5/s)") from err
    if rate <= 0:
        raise raw.error("rate (events per second) must be > 0")
    amp = raw.quantity("amp", sensor_dimension(sensor_type))
    width = 1.0
    if "width" in raw.values:
        width = raw.quantity("width", "dimensionless")
        if width < 1 or width != int(width):
            raise raw.error(f"width must be a whole number of samples >= 1, got {width:g}")
    return {"rate": rate, "amp": amp, "width": float(width)}


#: Per model: its parameters in SI (``Fault.params``) from the raw spec.
_MODEL_PARAMS: Final[dict[str, Callable[[_RawSpec, str, ArrayConfig], dict[str, float]]]] = {
    "step": _step_params,
    "drift": _drift_params,
    "noise": _noise_params,
    "stuck": _stuck_params,
    "scale": _scale_params,
    "spikes": _spikes_params,
}


def _build_fault(
    model: str,
    sensor: str,
    values: Mapping[str, Any],
    array: ArrayConfig,
    spec: str,
) -> Fault:
    """Validate one fault given as model, sensor and raw key -> value (str or number)."""
    raw = _RawSpec(model, values, f"fault {spec!r}")
    if model not in MODEL_KEYS:
        raise raw.error(f"unknown model {model!r}; valid: {', '.join(MODELS)}")
    valid_keys = MODEL_KEYS[model] | _COMMON_KEYS
    for key in values:
        if key not in valid_keys:
            raise raw.error(
                f"unknown key {key!r} for {model}; valid: {', '.join(sorted(valid_keys))}"
            )
    try:
        imu, sensor_type, axes = parse_sensor_id(sensor, array)
    except ArrayConfigError as err:
        raise raw.error(f"sensor: {err}") from err
    at_s, until_s = _window(raw)
    fault_id = _fault_id(raw)
    return Fault(
        model=model,
        sensors=[f"imu{imu}.{sensor_type}.{a}" for a in axes],
        at_s=at_s,
        until_s=until_s,
        params=_MODEL_PARAMS[model](raw, sensor_type, array),
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
    data = parse_toml(text, path, FaultSpecError)
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
