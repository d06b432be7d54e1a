"""The detector interface, its output, and typed parameters.

Every detector is one module with one class that follows :class:`Detector` and inherits
:class:`DetectorBase`, and is built one way, from its declared :class:`Param` specs::

    det = GltDetector.from_params({"alpha": "0.001"})   # or make_detector("glt", {...})
    det.fit(calibration_block, array)         # fault-free window: sigma, biases, ...
    for block in blocks:                       # consecutive ImuBlocks, streaming state inside
        out = det.process(block)               # {"gyro": DetectionBlock, "accel": ...}

``process`` returns, for every sensor type the detector tests, one DetectionBlock whose rows
are the oldest input samples not yet reported, in order. A causal detector returns one row
per input sample; a detector that needs look-ahead (e.g. windowed decompositions) may hold
samples back and returns them later; ``flush()`` returns every held-back row at the end of
the log, so that over ``process`` + ``flush`` each input sample gets exactly one row. The
pipeline pairs rows with timestamps in order.

Every detector declares ``lookahead_samples``: the largest number of later input samples the
decision on a sample may wait for (0 for a causal detector, whose row for sample i depends
on samples up to i only). The pipeline stamps each row with its decision time (see
:func:`imufdi_cli.detect.decision_positions`), so a detector that looks ahead pays for it in
the reported delays. Sensor indices refer to
``ArrayConfig.sensor_ids(sensor_type)`` (global, never renumbered by reconfiguration).

Construction: :meth:`DetectorBase.from_params` is the only place raw parameters (strings from
the CLI or campaign specs, or values) are checked, against the class's ``PARAMS``: unknown
names, kinds, bounds, choices and per-parameter checks. It then calls ``__init__`` with one
typed keyword argument per ``PARAMS`` entry, so ``__init__`` takes exactly those names (a
test checks every registered detector) and does not re-check them; it only checks
constraints between parameters (e.g. ``overlap < window``). The sensor types a detector
tests are its ``types`` parameter (:data:`TYPES`); a renamed parameter stays accepted
through ``RENAMED_PARAMS`` with a :class:`ParameterRenamedWarning` (docs/writing-a-detector.md).
"""

from __future__ import annotations

import functools
import math
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, Protocol, TypeVar, runtime_checkable

import numpy as np

from imufdi_cli.array import SENSOR_TYPES, ArrayConfig
from imufdi_cli.errors import DetectorConfigError, UnitError
from imufdi_cli.log import ImuBlock
from imufdi_cli.units import parse_quantity

#: ``isolated`` value when no sensor is isolated (no alarm, or not yet confirmed).
NO_ISOLATION = -1
#: ``isolated`` value when the configuration cannot isolate (e.g. 2 sensors on an axis).
NOT_ISOLABLE = -2


@dataclass
class DetectionBlock:
    """Per-sample output of a detector for one sensor type.

    Attributes
    ----------
    statistic : ndarray, shape (N,), float64
        Detection statistic (dimensionless unless the detector documents otherwise).
    threshold : ndarray, shape (N,), float64
        Threshold the statistic is compared to (may vary, e.g. after reconfiguration).
    alarm : ndarray, shape (N,), bool
        Fault declared at this sample (after any persistence logic).
    isolated : ndarray, shape (N,), int32
        Index of the isolated sensor in ``sensor_ids(type)``, or NO_ISOLATION (-1), or
        NOT_ISOLABLE (-2).
    amplitude : ndarray, shape (N,), float64
        Estimated fault amplitude of the isolated sensor, SI units; NaN when none.
    scores : ndarray, shape (N, n_s), float64
        Per-sensor isolation scores (e.g. D_FI,i); NaN where not computed.
    isolated_set : ndarray, shape (N, n_s), bool, or None
        Every sensor isolated at each sample, for detectors that isolate several
        simultaneous faults; None means "just ``isolated``" (see :meth:`isolation_set`).
    amplitudes : ndarray, shape (N, n_s), float64, or None
        Estimated fault amplitude of every sensor, SI units (NaN where not estimated), for
        detectors that identify several simultaneous faults; None means "just
        ``amplitude``, on the isolated sensor" (see :meth:`amplitude_set`).
    """

    statistic: np.ndarray
    threshold: np.ndarray
    alarm: np.ndarray
    isolated: np.ndarray
    amplitude: np.ndarray
    scores: np.ndarray
    isolated_set: np.ndarray | None = None
    amplitudes: np.ndarray | None = None

    def isolation_set(self) -> np.ndarray:
        """(N, n_s) bool: ``isolated_set``, or the one-hot of ``isolated`` when it is None."""
        if self.isolated_set is not None:
            return np.asarray(self.isolated_set, dtype=bool)
        n, n_sensors = self.scores.shape[0], self.scores.shape[1]
        out = np.zeros((n, n_sensors), dtype=bool)
        rows = np.flatnonzero(self.isolated >= 0)
        out[rows, self.isolated[rows]] = True
        return out

    def amplitude_set(self) -> np.ndarray:
        """(N, n_s) float64: ``amplitudes``, or ``amplitude`` on the column of ``isolated``
        (NaN elsewhere) when it is None."""
        if self.amplitudes is not None:
            return np.asarray(self.amplitudes, dtype=np.float64)
        n, n_sensors = self.scores.shape[0], self.scores.shape[1]
        out = np.full((n, n_sensors), np.nan)
        rows = np.flatnonzero((self.isolated >= 0) & (self.isolated < n_sensors))
        out[rows, self.isolated[rows]] = np.asarray(self.amplitude, dtype=np.float64)[rows]
        return out

    def __len__(self) -> int:
        return int(self.statistic.shape[0])

    @classmethod
    def empty(cls, n_samples: int, n_sensors: int) -> DetectionBlock:
        """All-quiet output: statistic 0, threshold inf, no alarm, no isolation."""
        return cls(
            statistic=np.zeros(n_samples),
            threshold=np.full(n_samples, np.inf),
            alarm=np.zeros(n_samples, dtype=bool),
            isolated=np.full(n_samples, NO_ISOLATION, dtype=np.int32),
            amplitude=np.full(n_samples, np.nan),
            scores=np.full((n_samples, n_sensors), np.nan),
        )

    @classmethod
    def concatenate(cls, blocks: list[DetectionBlock]) -> DetectionBlock:
        return cls(
            statistic=np.concatenate([b.statistic for b in blocks]),
            threshold=np.concatenate([b.threshold for b in blocks]),
            alarm=np.concatenate([b.alarm for b in blocks]),
            isolated=np.concatenate([b.isolated for b in blocks]),
            amplitude=np.concatenate([b.amplitude for b in blocks]),
            scores=np.concatenate([b.scores for b in blocks], axis=0),
            isolated_set=None
            if all(b.isolated_set is None for b in blocks)
            else np.concatenate([b.isolation_set() for b in blocks], axis=0),
            amplitudes=None
            if all(b.amplitudes is None for b in blocks)
            else np.concatenate([b.amplitude_set() for b in blocks], axis=0),
        )


@runtime_checkable
class Detector(Protocol):
    """What every detector implements (see module docstring)."""

    name: ClassVar[str]
    PARAMS: ClassVar[Mapping[str, Param]]
    #: Maximum number of input samples a row may be held back: the decision on sample i
    #: is available once sample i + lookahead_samples has been passed in (0: causal).
    lookahead_samples: int

    def fit(self, calibration: ImuBlock, array: ArrayConfig) -> None:
        """Learn noise, biases, thresholds from a fault-free calibration block."""
        ...

    def process(self, block: ImuBlock) -> dict[str, DetectionBlock]:
        """Test one block; returns one DetectionBlock per tested sensor type."""
        ...

    def flush(self) -> dict[str, DetectionBlock]:
        """Rows still held back at the end of the log (empty blocks for causal detectors)."""
        ...

    def metadata(self) -> dict[str, Any]:
        """JSON-ready parameters and calibration results (the ``imufdi.detect.<name>`` record)."""
        ...

    @classmethod
    def from_params(cls, raw: Mapping[str, Any] | None = None) -> Detector:
        """The detector built from raw parameters (see :meth:`DetectorBase.from_params`)."""
        ...


# --- typed parameters ------------------------------------------------------------------


@dataclass(frozen=True)
class Param:
    """A detector parameter: how to parse it from a string, its default, its bounds.

    ``kind`` is ``"float"``, ``"int"``, ``"bool"``, ``"str"``, ``"choice"``, ``"path"`` or a
    unit dimension of :mod:`imufdi_cli.units` (``"time"``, ``"angular_rate"``, ...), in
    which case strings like ``"2.5s"`` are accepted and stored in SI.
    """

    kind: str
    default: Any
    help: str
    low: float | None = None  # inclusive lower bound
    high: float | None = None  # inclusive upper bound
    low_open: bool = False  # lower bound exclusive
    choices: tuple[str, ...] = ()
    check: Callable[[Any], str | None] | None = field(default=None, compare=False)

    def parse(self, raw: Any, where: str) -> Any:
        value: Any
        try:
            if raw is None:
                return None
            if self.kind == "str" or self.kind == "path":
                value = str(raw)
            elif self.kind == "choice":
                value = str(raw)
                if value not in self.choices:
                    raise DetectorConfigError(
                        f"{where}: {value!r} is not valid; valid: {', '.join(self.choices)}"
                    )
            elif self.kind == "bool":
                if isinstance(raw, bool):
                    value = raw
                elif str(raw).lower() in ("1", "true", "yes", "on"):
                    value = True
                elif str(raw).lower() in ("0", "false", "no", "off"):
                    value = False
                else:
                    raise DetectorConfigError(f"{where}: {raw!r} is not a boolean (true/false)")
            elif self.kind == "int":
                if isinstance(raw, float) and not raw.is_integer():
                    raise ValueError
                value = int(str(raw)) if not isinstance(raw, (int, float)) else int(raw)
            elif self.kind == "float":
                value = float(raw)
                if not math.isfinite(value):
                    raise ValueError
            else:
                value = parse_quantity(raw, self.kind, name=where)
        except UnitError as err:
            raise DetectorConfigError(str(err)) from err
        except (TypeError, ValueError):
            raise DetectorConfigError(f"{where}: {raw!r} is not a valid {self.kind}") from None
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            if self.low is not None and (value < self.low or (self.low_open and value <= self.low)):
                op = ">" if self.low_open else ">="
                raise DetectorConfigError(f"{where}: must be {op} {self.low}, got {raw!r}")
            if self.high is not None and value > self.high:
                raise DetectorConfigError(f"{where}: must be <= {self.high}, got {raw!r}")
        if self.check is not None:
            problem = self.check(value)
            if problem:
                raise DetectorConfigError(f"{where}: {problem}")
        return value


def parse_params(
    specs: Mapping[str, Param], raw: Mapping[str, Any], detector: str
) -> dict[str, Any]:
    """Typed parameter values: defaults overridden by ``raw`` (strings or values).

    Raises DetectorConfigError for an unknown name (listing the valid ones) or a bad value.
    """
    for key in raw:
        if key not in specs:
            valid = ", ".join(sorted(specs)) or "(none)"
            raise DetectorConfigError(f"unknown parameter {detector}.{key}; valid: {valid}")
    values: dict[str, Any] = {}
    for key, spec in specs.items():
        if key in raw:
            values[key] = spec.parse(raw[key], f"{detector}.{key}")
        else:
            values[key] = spec.default
    return values


class ParameterRenamedWarning(FutureWarning):
    """A detector parameter was given under its old name (still accepted, to be removed).

    A FutureWarning, so Python shows it by default; ``imufdi detect`` turns it into a
    ``warning:`` line on stderr (:func:`imufdi_cli.detectors.make_detectors`).
    """


_D = TypeVar("_D", bound="DetectorBase")


class DetectorBase:
    """The construction every detector shares: :meth:`from_params`.

    A detector class inherits this and declares ``name``, ``PARAMS`` and an ``__init__``
    whose keyword arguments are exactly the ``PARAMS`` names, with the same defaults.
    """

    name: ClassVar[str]
    PARAMS: ClassVar[Mapping[str, Param]]
    #: Old parameter name -> current name; the old name is accepted with a
    #: :class:`ParameterRenamedWarning`.
    RENAMED_PARAMS: ClassVar[Mapping[str, str]] = {}

    @classmethod
    def from_params(cls: type[_D], raw: Mapping[str, Any] | None = None) -> _D:
        """Build the detector from raw parameters (strings as on the command line, or values).

        Renamed parameters are mapped to their current name (with a warning), then every
        value is parsed and checked by :func:`parse_params` against ``PARAMS``; omitted ones
        take their defaults.

        Raises
        ------
        DetectorConfigError
            Unknown parameter (the message lists the valid ones), a value of the wrong kind
            or out of bounds, a parameter given under both names, or an inconsistent
            combination (checked by ``__init__``).
        """
        given = _current_names(cls, dict(raw or {}), stacklevel=3)
        return cls(**parse_params(cls.PARAMS, given, cls.name))

    def __init_subclass__(cls, **kwargs: Any) -> None:
        """A class with ``RENAMED_PARAMS`` also accepts the old names as keywords of its
        constructor (Python callers), with the same warning as :meth:`from_params`."""
        super().__init_subclass__(**kwargs)
        init = cls.__dict__.get("__init__")
        if not cls.RENAMED_PARAMS or init is None:
            return

        @functools.wraps(init)
        def accepting_old_names(self: Any, *args: Any, **given: Any) -> None:
            init(self, *args, **_current_names(type(self), given, stacklevel=3))

        cls.__init__ = accepting_old_names  # type: ignore[method-assign]


def _current_names(
    cls: type[DetectorBase], given: dict[str, Any], *, stacklevel: int
) -> dict[str, Any]:
    """``given`` with renamed parameters under their current names (one warning each)."""
    for old, new in cls.RENAMED_PARAMS.items():
        if old not in given:
            continue
        if new in given:
            raise DetectorConfigError(
                f"{cls.name}: give {new} only ({old} is its deprecated old name)"
            )
        warnings.warn(
            f"{cls.name}.{old} is deprecated; use {cls.name}.{new}",
            ParameterRenamedWarning,
            stacklevel=stacklevel,
        )
        given[new] = given.pop(old)
    return given


def sensor_types_problem(text: Any) -> str | None:
    """Why ``text`` is not a comma list of sensor types, or None (a :attr:`Param.check`)."""
    types = [item.strip() for item in str(text).split(",") if item.strip()]
    for item in types:
        if item not in SENSOR_TYPES:
            return f"unknown sensor type {item!r}; valid: {', '.join(SENSOR_TYPES)}"
    if not types:
        return f"give at least one of {', '.join(SENSOR_TYPES)}"
    return None


def parse_sensor_types(text: str, detector: str) -> tuple[str, ...]:
    """``"gyro,accel"`` -> ``("gyro", "accel")`` for a detector's ``types`` parameter.

    Raises DetectorConfigError naming the valid types for an unknown or empty list.
    """
    problem = sensor_types_problem(text)
    if problem:
        raise DetectorConfigError(f"{detector}.types: {problem}")
    return tuple(item.strip() for item in text.split(",") if item.strip())


TYPES = Param(
    "str",
    "gyro,accel",
    "sensor types to test, comma-separated (gyro, accel, mag)",
    check=sensor_types_problem,
)
"""The common ``types`` parameter: which sensor types a detector tests (parse it with
:func:`parse_sensor_types`). Detectors that accept only some types, or ``auto``, declare
their own ``types`` Param with another default or check, under the same name."""

ALPHA = Param("float", 0.01, "false-alarm level of the test", low=0.0, high=0.5, low_open=True)
"""The common ``alpha`` parameter (0 < alpha <= 0.5)."""

FALSE_ALARMS = Param(
    "frequency",
    0.0,
    "false-alarm budget: expected false alarm episodes per unit of fault-free time on each"
    " status channel, e.g. 1/h (0: the per-sample test at alpha)",
    low=0.0,
)
"""The common ``false_alarms`` parameter (``imufdi detect --false-alarms RATE``), in SI
(episodes per second; ``"1/h"`` is 1/3600). 0 keeps the per-sample test at ``alpha``; a
positive budget makes the detector decide so that a fault-free log raises at most that many
false alarm episodes per unit of time on each of its status channels (docs/guide.md)."""


def calibration_stats(values: np.ndarray, min_samples: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Per-sensor mean and standard deviation of a fault-free window.

    Parameters
    ----------
    values : ndarray, shape (N, n)
    min_samples : int
        Fewer samples than this raise CalibrationError.

    Returns
    -------
    mean, std : ndarray, shape (n,)
    """
    from imufdi_cli.errors import CalibrationError

    if values.shape[0] < min_samples:
        raise CalibrationError(
            f"calibration window has {values.shape[0]} samples; at least {min_samples} are needed"
            " (use --calibrate START:END to choose a longer fault-free window)"
        )
    mean = values.mean(axis=0)
    std = values.std(axis=0, ddof=1)
    return mean, std
