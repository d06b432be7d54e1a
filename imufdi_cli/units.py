"""Quantities with units, typed by users, to SI floats.

``parse_quantity("0.9deg/s", "angular_rate")`` returns ``0.015707963...`` (rad/s).
Supported grammar: a float, optional white space, then a unit expression made of unit
symbols joined by ``*`` or ``/`` with optional integer powers (``^2`` or ``2``), e.g.
``deg/s^2``, ``m/s/s``, ``g/s``, ``rad/s``, ``deg/h``, ``uT``, ``kHz``, and a count per
unit of time such as ``1/h`` or ``5/min`` (a frequency). Units as people type them are
read too: ``°/s``, ``m/s²``, ``µT`` (micro sign or Greek mu), ``%`` (0.01) and ``·``. A
bare number is taken as SI for the requested dimension. ``g`` is standard gravity and
``G`` gauss (as magnetometer datasheets write it); ``16G`` where an acceleration is
expected is refused with that hint.

Dimensions are vectors over (m, s, rad, T); radians are kept as a dimension so that an
angular rate cannot be typed where an acceleration is expected.
"""

from __future__ import annotations

import math
import re
from typing import Final

from imufdi_cli.errors import UnitError

# exponent vectors over (metre, second, radian, tesla)
_Dim = tuple[int, int, int, int]

DIMENSIONS: Final[dict[str, _Dim]] = {
    "time": (0, 1, 0, 0),
    "frequency": (0, -1, 0, 0),
    "angle": (0, 0, 1, 0),
    "angular_rate": (0, -1, 1, 0),
    "angular_acceleration": (0, -2, 1, 0),
    "velocity": (1, -1, 0, 0),
    "acceleration": (1, -2, 0, 0),
    "jerk": (1, -3, 0, 0),
    "magnetic_field": (0, 0, 0, 1),
    "magnetic_rate": (0, -1, 0, 1),
    "length": (1, 0, 0, 0),
    "dimensionless": (0, 0, 0, 0),
}

STANDARD_GRAVITY: Final[float] = 9.80665  # m/s^2

# symbol -> (factor to SI, dimension)
_UNITS: Final[dict[str, tuple[float, _Dim]]] = {
    "s": (1.0, (0, 1, 0, 0)),
    "sec": (1.0, (0, 1, 0, 0)),
    "ms": (1e-3, (0, 1, 0, 0)),
    "us": (1e-6, (0, 1, 0, 0)),
    "ns": (1e-9, (0, 1, 0, 0)),
    "min": (60.0, (0, 1, 0, 0)),
    "h": (3600.0, (0, 1, 0, 0)),
    "hr": (3600.0, (0, 1, 0, 0)),
    "Hz": (1.0, (0, -1, 0, 0)),
    "kHz": (1e3, (0, -1, 0, 0)),
    "rad": (1.0, (0, 0, 1, 0)),
    "mrad": (1e-3, (0, 0, 1, 0)),
    "deg": (math.pi / 180.0, (0, 0, 1, 0)),
    "dps": (math.pi / 180.0, (0, -1, 1, 0)),
    "rpm": (2.0 * math.pi / 60.0, (0, -1, 1, 0)),
    "m": (1.0, (1, 0, 0, 0)),
    "mm": (1e-3, (1, 0, 0, 0)),
    "cm": (1e-2, (1, 0, 0, 0)),
    "g": (STANDARD_GRAVITY, (1, -2, 0, 0)),
    "mg": (STANDARD_GRAVITY * 1e-3, (1, -2, 0, 0)),
    "ug": (STANDARD_GRAVITY * 1e-6, (1, -2, 0, 0)),
    "T": (1.0, (0, 0, 0, 1)),
    "mT": (1e-3, (0, 0, 0, 1)),
    "uT": (1e-6, (0, 0, 0, 1)),
    "nT": (1e-9, (0, 0, 0, 1)),
    "G": (1e-4, (0, 0, 0, 1)),  # gauss (magnetometer datasheets); g is standard gravity
    "mG": (1e-7, (0, 0, 0, 1)),
    "percent": (0.01, (0, 0, 0, 0)),
}

#: how people type units -> the ASCII symbols above (``°/s``, ``m/s²``, ``µT``, ``%``)
_TYPED: Final[tuple[tuple[str, str], ...]] = (
    ("°", "deg"),
    ("µ", "u"),  # micro sign
    ("μ", "u"),  # Greek mu
    ("²", "^2"),
    ("³", "^3"),
    ("·", "*"),
    ("%", "percent"),
)


def _ascii_unit(unit: str) -> str:
    for typed, symbol in _TYPED:
        unit = unit.replace(typed, symbol)
    return unit


_NUMBER = re.compile(r"^\s*([+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)\s*(.*?)\s*$")
_FACTOR = re.compile(r"^([A-Za-z]+)(?:\^?([+-]?\d+))?$")


def _parse_unit(expr: str) -> tuple[float, _Dim]:
    factor = 1.0
    dim = [0, 0, 0, 0]
    # split on * and /, keeping the operator
    tokens = re.split(r"([*/])", expr.replace(" ", ""))
    sign = 1
    for token in tokens:
        if token == "*":
            sign = 1
            continue
        if token == "/":
            sign = -1
            continue
        if token == "":
            raise UnitError(f"malformed unit expression {expr!r}")
        if token == "1" and sign == 1:  # the "1" of "1/h"
            continue
        match = _FACTOR.match(token)
        if match is None or match.group(1) not in _UNITS:
            name = match.group(1) if match else token
            raise UnitError(
                f"unknown unit {name!r} in {expr!r}; known units: {', '.join(sorted(_UNITS))}"
            )
        unit_factor, unit_dim = _UNITS[match.group(1)]
        power = int(match.group(2)) if match.group(2) else 1
        factor *= unit_factor ** (sign * power)
        for i in range(4):
            dim[i] += sign * power * unit_dim[i]
        sign = 1
    return factor, (dim[0], dim[1], dim[2], dim[3])


def parse_quantity(text: str | float | int, dimension: str, *, name: str = "value") -> float:
    """Parse a quantity typed by a user into an SI float.

    Parameters
    ----------
    text : str or float
        e.g. ``"0.9deg/s"``, ``"2.5s"``, ``"0.1g"``, ``"3e-3rad/s^2"``; a bare number is SI.
    dimension : str
        One of :data:`DIMENSIONS` (``"angular_rate"``, ``"time"``, ...).
    name : str
        What the value is, for error messages (``"amp"``, ``"--duration"``).

    Returns
    -------
    float
        The value in SI units (rad/s, s, m/s^2, T, ...).

    Raises
    ------
    UnitError
        Unknown unit, malformed number or wrong dimension.
    """
    if dimension not in DIMENSIONS:
        raise ValueError(f"unknown dimension {dimension!r}")
    if isinstance(text, (int, float)) and not isinstance(text, bool):
        try:
            value = float(text)
        except OverflowError as err:  # an integer beyond any float (TOML and JSON allow them)
            raise UnitError(f"{name}: {str(text)[:20]}... is not a finite number") from err
        if not math.isfinite(value):
            raise UnitError(f"{name}: {text!r} is not a finite number")
        return value
    match = _NUMBER.match(str(text))
    if match is None:
        raise UnitError(
            f"{name}: cannot read {text!r} as a number with a unit (e.g. {example(dimension)})"
        )
    value = float(match.group(1))
    unit = _ascii_unit(match.group(2))
    if not unit:
        if not math.isfinite(value):
            raise UnitError(f"{name}: {text!r} is not a finite number")
        return value
    if unit.startswith("/"):  # "1/h", "5/min": a count per unit of time
        unit = "1" + unit
    factor, dim = _parse_unit(unit)
    if dim != DIMENSIONS[dimension]:
        label = dimension.replace("_", " ")
        article = "an" if label[0] in "aeiou" else "a"
        hint = ""
        if re.search(r"(^|[^A-Za-z])m?G([^A-Za-z]|$)", unit) and dimension in (
            "acceleration",
            "jerk",
        ):
            hint = "; G is gauss (a magnetic field): write g for standard gravity (16g)"
        raise UnitError(
            f"{name}: {text!r} is not {article} {label} (e.g. {example(dimension)}){hint}"
        )
    if not math.isfinite(value * factor):  # "1e400deg/s"
        raise UnitError(f"{name}: {text!r} is not a finite number")
    return value * factor


_EXAMPLES: Final[dict[str, str]] = {
    "time": "2.5s, 500ms",
    "frequency": "100Hz, 1kHz, 1/h, 5/min",
    "angle": "30deg, 0.5rad",
    "angular_rate": "0.9deg/s, 0.9°/s, 0.01rad/s",
    "angular_acceleration": "10deg/s^2, 3e-3rad/s^2",
    "acceleration": "0.1g, 0.5m/s^2, 0.5m/s²",
    "jerk": "0.01g/s, 0.1m/s^3",
    "magnetic_field": "50uT, 50µT, 0.5G",
    "magnetic_rate": "1uT/s",
    "length": "0.05m, 30mm",
    "dimensionless": "1.5, 150%",
}


def example(dimension: str) -> str:
    """Examples of valid strings for a dimension, for error messages."""
    return _EXAMPLES.get(dimension, "a number")


def sensor_dimension(sensor_type: str) -> str:
    """The dimension of a sensor type's measurements (``gyro`` -> ``angular_rate``)."""
    try:
        return {"gyro": "angular_rate", "accel": "acceleration", "mag": "magnetic_field"}[
            sensor_type
        ]
    except KeyError:
        raise UnitError(f"unknown sensor type {sensor_type!r}; valid: gyro, accel, mag") from None


def rate_dimension(sensor_type: str) -> str:
    """The dimension of a sensor type's drift rate (``gyro`` -> ``angular_acceleration``)."""
    return {
        "angular_rate": "angular_acceleration",
        "acceleration": "jerk",
        "magnetic_field": "magnetic_rate",
    }[sensor_dimension(sensor_type)]


def parse_time_range(text: str, *, name: str = "window") -> tuple[float, float | None]:
    """Parse ``"0s:2s"``, ``"1.5s:"``, ``":2s"`` into ``(start_s, end_s or None)``."""
    if ":" not in text:
        raise UnitError(f"{name}: {text!r} is not a time range START:END (e.g. 0s:2s)")
    start_text, end_text = text.split(":", 1)
    start = parse_quantity(start_text, "time", name=name) if start_text.strip() else 0.0
    end = parse_quantity(end_text, "time", name=name) if end_text.strip() else None
    if start < 0 or (end is not None and end <= start):
        raise UnitError(f"{name}: {text!r} must satisfy 0 <= START < END")
    return start, end


class UnixTime(float):
    """An absolute time, seconds since 1970-01-01 UTC, among times that are otherwise
    seconds from the log start (``--start 2023-11-14T22:13:30Z``, ``--start 1700000010``).
    A float, so a window holding one is still ``(start_s, end_s)``; resolve it against the
    log's first sample with :func:`from_log_start`."""

    __slots__ = ()


#: a bare number at least this large is a Unix time (2001-09-09), not seconds from the
#: log start: no log lasts 31 years, and a viewer's times are Unix times
UNIX_TIME_MIN_S: Final[float] = 1e9

_ISO = re.compile(
    r"^\d{4}-\d{2}-\d{2}[T ]\d{2}:\d{2}(:\d{2}(\.\d+)?)?(Z|[+-]\d{2}(:?\d{2})?)?$", re.IGNORECASE
)


def parse_time_point(text: str, *, name: str = "time") -> float:
    """A point in a log: seconds from its start (``30``, ``30s``, ``2min``), an ISO 8601
    UTC time (``2023-11-14T22:13:30Z``, ``+01:00`` offsets too) or a Unix time (a bare
    number >= 1e9, e.g. ``1700000010.5``); the last two as :class:`UnixTime`.

    Raises
    ------
    UnitError
        Not one of these forms, or an ISO time without a time zone.
    """
    stripped = str(text).strip()
    if _ISO.match(stripped):
        from datetime import datetime

        if not re.search(r"(Z|[+-]\d{2}(:?\d{2})?)$", stripped, re.IGNORECASE):
            raise UnitError(
                f"{name}: {text!r} has no time zone; add Z for UTC (e.g."
                f" {stripped}Z) or an offset such as +01:00"
            )
        try:  # a trailing Z as +00:00: Python 3.10's fromisoformat reads no Z
            moment = datetime.fromisoformat(re.sub(r"[Zz]$", "+00:00", stripped))
        except ValueError as err:
            raise UnitError(f"{name}: {text!r} is not a valid ISO 8601 time ({err})") from None
        return UnixTime(moment.timestamp())
    try:
        bare = float(stripped)
    except ValueError:
        bare = None
    if bare is not None and math.isfinite(bare) and bare >= UNIX_TIME_MIN_S:
        return UnixTime(bare)
    try:
        return parse_quantity(stripped, "time", name=name)
    except UnitError:
        raise UnitError(
            f"{name}: cannot read {text!r} as a time; give seconds from the log start (30s,"
            " 2min), an ISO 8601 UTC time (2023-11-14T22:13:30Z) or a Unix time"
            " (1700000010)"
        ) from None


def from_log_start(value: float, origin_ns: int) -> float:
    """Seconds from the log start of a time point: ``value`` itself, or a
    :class:`UnixTime` minus the log's first sample ``origin_ns`` (ns since the epoch)."""
    if isinstance(value, UnixTime):
        return float(value) - origin_ns * 1e-9
    return float(value)


def window_from_log_start(
    window: tuple[float, float | None], origin_ns: int
) -> tuple[float, float | None]:
    """``(start_s, end_s)`` with every :class:`UnixTime` resolved (:func:`from_log_start`)."""
    start, end = window
    return from_log_start(start, origin_ns), (
        None if end is None else from_log_start(end, origin_ns)
    )


def utc_iso(t_ns: int) -> str:
    """A time in ns since the epoch as ISO 8601 UTC: ``2023-11-14T22:13:20Z``, with
    milliseconds when it is not a whole second (``...:20.125Z``)."""
    from datetime import datetime, timezone

    seconds, rest = divmod(int(t_ns), 1_000_000_000)
    text = datetime.fromtimestamp(seconds, tz=timezone.utc).strftime("%Y-%m-%dT%H:%M:%S")
    if rest:
        text += f".{rest // 1_000_000:03d}"
    return text + "Z"
