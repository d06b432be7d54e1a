"""The fault models and :class:`Fault`, one fault resolved to SI (part of
:mod:`imufdi_cli.faults`; the models are described in its docstring).
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Final

import numpy as np

from imufdi_cli.errors import TruthError

#: Name of the MCAP metadata record describing injected faults.
METADATA_NAME: Final[str] = "imufdi.faults"
#: Topic of the ground-truth channel (one message per fault start/end).
TRUTH_TOPIC: Final[str] = "/imufdi/truth"
#: Schema name (ros2msg) of the ground-truth channel.
TRUTH_SCHEMA: Final[str] = "imufdi_msgs/msg/FaultEvent"
METADATA_FORMAT: Final[str] = "imufdi.faults/1"

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


#: a full sensor id, as fault records list them
_SENSOR_ID = re.compile(r"imu\d{1,6}\.(gyro|accel|mag)\.[xyz]")


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
        from imufdi_cli.array import AXES  # (the array module is not needed to read truth)

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
            if not sensors or not all(_SENSOR_ID.fullmatch(s) for s in sensors):
                raise TruthError(
                    f"fault record: bad sensors {data['sensors']!r}; each must be"
                    " imu<k>.<gyro|accel|mag>.<x|y|z>"
                )
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
