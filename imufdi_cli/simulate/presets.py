"""Reference scenarios (docs/simulate.md), their overrides, and validated construction from CLI
options (part of :mod:`imufdi_cli.simulate`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from typing import Any, Final

import numpy as np

from imufdi_cli.array import SENSOR_TYPES, ArrayConfig, ImuSpec
from imufdi_cli.errors import UnitError, UsageError
from imufdi_cli.simulate.errors import DEFAULT_MAGNETIC_FIELD, SensorErrors, SimConfig
from imufdi_cli.simulate.motions import (
    AttitudeMotion,
    SwingMotion,
    TurntableMotion,
    make_motion,
    rotation_from_euler,
)
from imufdi_cli.units import STANDARD_GRAVITY, parse_quantity, sensor_dimension

_DEG = math.pi / 180.0


# ==========================================================================================
# Presets (docs/simulate.md, "Reference presets")
# ==========================================================================================


@dataclass(frozen=True)
class PresetInfo:
    """A reference scenario.

    Attributes
    ----------
    name : str
    description : str
        One line: array, motion, errors.
    source : str
        The paper (and section) the scenario reproduces.
    faults : dict
        Benchmark scenario name -> list of fault spec strings (faults.py grammar).
    """

    name: str
    description: str
    source: str
    faults: Mapping[str, tuple[str, ...]]


PRESETS: Final[dict[str, PresetInfo]] = {
    "paper-table4": PresetInfo(
        name="paper-table4",
        description=(
            "16 co-aligned IMUs, 100 Hz, 5 s, turntable 10 deg/s on x, y and z; gyro sigma "
            "0.15 deg/s, accel sigma 0.02 m/s^2 white; gyro outliers p=0.001, +-1 deg/s"
        ),
        source="Li et al., Micromachines 17(3):374, 2026, §3 (Table 4)",
        faults={
            "step": ("step:imu0.gyro.x,at=2.5s,amp=0.9deg/s",),
            "drift": ("drift:imu0.gyro.x,at=2.5s,rate=10deg/s^2",),
        },
    ),
    "conical6": PresetInfo(
        name="conical6",
        description=(
            "6 single-axis gyros on a 54.7356 deg cone around body z (60 deg apart), no "
            "accelerometers, 100 Hz, 10 s; static 0-1 s then swinging tens of deg/s; bias "
            "0.1 deg/s, scale 500 ppm, misalignment 0.5 mrad (1-sigma), noise 0.03 deg/s"
        ),
        source="Hao & Wang, PCA with parity vectors for redundant IMUs in vehicle navigation, §4",
        faults={"bias": ("step:imu5.gyro.z,at=6s,amp=0.5deg/s",)},
    ),
    "wearable12": PresetInfo(
        name="wearable12",
        description=(
            "12 co-aligned IMUs on a 4x3 grid (3 cm pitch) 30 cm below a pivot, 100 Hz, 30 s, "
            "limb-like swing (30 deg at 1 Hz); accel sigma 0.03 m/s^2, gyro 0.1 deg/s"
        ),
        source="Chen, Su, Xu, accelerometer noise increase in wearable IMU arrays, §3",
        faults={"noise-growth": ("noise:imu0.accel.x,at=12s,until=18s,factor=3",)},
    ),
    "quadrotor-marg": PresetInfo(
        name="quadrotor-marg",
        description=(
            "1 MARG IMU (gyro, accel, mag), 100 Hz, 10 s, hovering; attitude "
            "[-25,-35,-10] deg -> 0 over 1-2 s -> [10,-20,5] deg over 5-6 s; gyro 0.01 rad/s, "
            "accel 0.002 g, mag 0.0007 of |h| (h = 50 uT along [1/2, 0, sqrt(3)/2])"
        ),
        source="Berbra, Gentil, Lesecq, Identification of multiple faults in an IMU, §2-3",
        faults={
            "accel-bias": ("step:imu0.accel.x,at=5s,amp=0.5g",),
            "gyro-bias": ("step:imu0.gyro.z,at=5s,amp=0.1rad/s",),
            "gyro-bias-drift": (
                "step:imu0.gyro.z,at=5s,amp=0.5rad/s",
                "drift:imu0.gyro.x,at=5s,rate=0.1rad/s^2",
            ),
        },
    ),
}

CONE_HALF_ANGLE: Final[float] = math.acos(1.0 / math.sqrt(3.0))  # 54.7356 deg


def conical_array(n_gyros: int = 6, rate_hz: float = 100.0) -> ArrayConfig:
    """Single-axis gyros (IMU z axis only) on a cone of half-angle arccos(1/sqrt(3)) around
    body z, evenly spaced in azimuth (gyro k at ``360 k / n`` deg). IMU k's frame is
    ``Rz(azimuth_k) Ry(half_angle)``, so its z axis is the sensing direction."""
    imus = []
    for k in range(n_gyros):
        rotation = rotation_from_euler(0.0, CONE_HALF_ANGLE, 2.0 * math.pi * k / n_gyros)
        imus.append(
            ImuSpec(
                rotation=np.asarray(rotation),
                position=np.zeros(3),
                axes={"gyro": ("z",), "accel": (), "mag": ()},
            )
        )
    return ArrayConfig(imus=tuple(imus), rate_hz=rate_hz)


def grid_positions(n_imus: int, pitch: float = 0.03) -> np.ndarray:
    """Positions (n, 3) m of n IMUs on a board grid (4 per row, rows along y), centred."""
    columns = min(4, n_imus)
    rows = -(-n_imus // columns)
    index = np.arange(n_imus)
    x = (index % columns - (columns - 1) / 2.0) * pitch
    y = (index // columns - (rows - 1) / 2.0) * pitch
    return np.stack([x, y, np.zeros(n_imus)], axis=-1)


def _paper_table4(n_imus: int | None) -> SimConfig:
    array = ArrayConfig.co_aligned(
        16 if n_imus is None else n_imus, 100.0, sensors=("gyro", "accel")
    )
    return SimConfig(
        array=array,
        duration_s=5.0,
        motion=TurntableMotion(rate=(10 * _DEG, 10 * _DEG, 10 * _DEG)),
        errors={
            "gyro": SensorErrors(
                noise=0.15 * _DEG, outlier_probability=0.001, outlier_amplitude=1.0 * _DEG
            ),
            "accel": SensorErrors(noise=0.02),
        },
        name="paper-table4",
    )


def _conical6(n_imus: int | None) -> SimConfig:
    return SimConfig(
        array=conical_array(6 if n_imus is None else n_imus, 100.0),
        duration_s=10.0,
        motion=SwingMotion(
            amplitude=(20 * _DEG, 15 * _DEG, 30 * _DEG),
            frequency_hz=(0.5, 0.35, 0.25),
            phase=(0.0, 0.8, 2.1),
            pivot_offset=(0.0, 0.0, 0.0),
            start=1.0,
            ramp=0.5,
        ),
        errors={
            "gyro": SensorErrors(
                noise=0.03 * _DEG,
                chip_bias_sigma=0.1 * _DEG,
                scale_factor_sigma=500e-6,
                misalignment_sigma=0.5e-3,
            )
        },
        name="conical6",
    )


def _wearable12(n_imus: int | None) -> SimConfig:
    n = 12 if n_imus is None else n_imus
    array = ArrayConfig.co_aligned(n, 100.0, sensors=("gyro", "accel"), positions=grid_positions(n))
    return SimConfig(
        array=array,
        duration_s=30.0,
        motion=SwingMotion(
            amplitude=(30 * _DEG, 8 * _DEG, 5 * _DEG),
            frequency_hz=(1.0, 0.8, 0.45),
            phase=(0.0, 0.6, 1.7),
            pivot_offset=(0.0, 0.0, -0.3),
            start=0.0,
            ramp=1.0,
        ),
        errors={"gyro": SensorErrors(noise=0.1 * _DEG), "accel": SensorErrors(noise=0.03)},
        name="wearable12",
    )


def _quadrotor_marg(n_imus: int | None) -> SimConfig:
    n = 1 if n_imus is None else n_imus
    array = ArrayConfig.co_aligned(n, 100.0, sensors=("gyro", "accel", "mag"))
    field_magnitude = float(np.linalg.norm(DEFAULT_MAGNETIC_FIELD))
    return SimConfig(
        array=array,
        duration_s=10.0,
        motion=AttitudeMotion(
            initial_rpy=(-25 * _DEG, -35 * _DEG, -10 * _DEG),
            moves=(
                (1.0, 1.0, (0.0, 0.0, 0.0)),
                (5.0, 1.0, (10 * _DEG, -20 * _DEG, 5 * _DEG)),
            ),
        ),
        errors={
            "gyro": SensorErrors(noise=0.01),
            "accel": SensorErrors(noise=0.002 * STANDARD_GRAVITY),
            "mag": SensorErrors(noise=0.0007 * field_magnitude),
        },
        magnetic_field=DEFAULT_MAGNETIC_FIELD,
        name="quadrotor-marg",
    )


#: Preset name -> its SimConfig for a number of IMUs (None: the preset's own).
_PRESET_BUILDERS: Final[dict[str, Callable[[int | None], SimConfig]]] = {
    "paper-table4": _paper_table4,
    "conical6": _conical6,
    "wearable12": _wearable12,
    "quadrotor-marg": _quadrotor_marg,
}


def _preset_base(name: str, n_imus: int | None) -> SimConfig:
    if name not in _PRESET_BUILDERS:
        raise UsageError(f"unknown preset {name!r}; valid: {', '.join(sorted(PRESETS))}")
    return _PRESET_BUILDERS[name](n_imus)


PRESET_OVERRIDES: Final[tuple[str, ...]] = (
    "duration",
    "rate",
    "n_imus",
    "outliers",
    "chip_biases",
    "noise_scale",
    "gyro_noise",
    "accel_noise",
    "mag_noise",
    "t0_ns",
)


def _positive(value: Any, dimension: str, name: str) -> float:
    try:
        number = parse_quantity(value, dimension, name=name)
    except UnitError as err:
        raise UsageError(str(err)) from err
    if not number > 0:
        raise UsageError(f"{name} must be > 0, got {value!r}")
    return number


def _non_negative(value: Any, dimension: str, name: str) -> float:
    try:
        number = parse_quantity(value, dimension, name=name)
    except UnitError as err:
        raise UsageError(str(err)) from err
    if not number >= 0:
        raise UsageError(f"{name} must be >= 0, got {value!r}")
    return number


def _with_errors(config: SimConfig, sensor_type: str, **changes: Any) -> SimConfig:
    errors = dict(config.errors)
    errors[sensor_type] = replace(errors.get(sensor_type, SensorErrors()), **changes)
    return replace(config, errors=errors)


def apply_overrides(config: SimConfig, **overrides: Any) -> SimConfig:
    """Apply preset overrides (see :func:`preset`) to a config; ``None`` values are ignored."""
    for key in overrides:
        if key not in PRESET_OVERRIDES:
            raise UsageError(
                f"unknown simulation option {key!r}; valid: {', '.join(PRESET_OVERRIDES)}"
            )
    given = {k: v for k, v in overrides.items() if v is not None}
    if "duration" in given:
        config = replace(config, duration_s=_positive(given["duration"], "time", "duration"))
    if "rate" in given:
        rate = _positive(given["rate"], "frequency", "rate")
        config = replace(
            config,
            array=ArrayConfig(imus=config.array.imus, rate_hz=rate, noise=config.array.noise),
        )
    if "t0_ns" in given:
        t0 = given["t0_ns"]
        if not isinstance(t0, (int, np.integer)) or isinstance(t0, bool) or t0 < 0:
            raise UsageError(f"t0_ns must be an integer >= 0 (ns), got {t0!r}")
        config = replace(config, t0_ns=int(t0))
    if "noise_scale" in given:
        scale = _non_negative(given["noise_scale"], "dimensionless", "noise_scale")
        for sensor_type, errors in list(config.errors.items()):
            config = _with_errors(config, sensor_type, noise=errors.noise * scale)
    for sensor_type in SENSOR_TYPES:
        key = f"{sensor_type}_noise"
        if key in given:
            sigma = _non_negative(given[key], sensor_dimension(sensor_type), key)
            config = _with_errors(config, sensor_type, noise=sigma)
    if "outliers" in given:
        value = given["outliers"]
        gyro = config.errors.get("gyro", SensorErrors())
        if isinstance(value, bool):
            probability = (gyro.outlier_probability or 0.001) if value else 0.0
        else:
            try:
                probability = float(value)
            except (TypeError, ValueError) as err:
                raise UsageError(
                    f"outliers must be true/false or a probability in [0, 1], got {value!r}"
                ) from err
            if not 0.0 <= probability <= 1.0:
                raise UsageError(f"outliers probability must be in [0, 1], got {value!r}")
        amplitude = gyro.outlier_amplitude or 1.0 * _DEG
        config = _with_errors(
            config, "gyro", outlier_probability=probability, outlier_amplitude=amplitude
        )
    if "chip_biases" in given:
        value = given["chip_biases"]
        per_type = value if isinstance(value, Mapping) else {"gyro": value}
        for sensor_type, sigma_raw in per_type.items():
            if sensor_type not in SENSOR_TYPES:
                raise UsageError(
                    f"chip_biases: unknown sensor type {sensor_type!r}; valid: "
                    + ", ".join(SENSOR_TYPES)
                )
            sigma = _non_negative(
                sigma_raw, sensor_dimension(sensor_type), f"chip_biases.{sensor_type}"
            )
            config = _with_errors(config, sensor_type, chip_bias_sigma=sigma)
    return _with_nominal_noise(config)


def _with_nominal_noise(config: SimConfig) -> SimConfig:
    """Copy the white-noise sigmas into ``array.noise`` (nominal noise for detectors)."""
    noise = {
        s: float(e.noise) for s, e in config.errors.items() if config.array.has(s) and e.noise > 0
    }
    array = ArrayConfig(imus=config.array.imus, rate_hz=config.array.rate_hz, noise=noise)
    return replace(config, array=array)


def preset(name: str, *, seed: int = 0, **overrides: Any) -> SimConfig:
    """The SimConfig of a reference scenario (docs/simulate.md), optionally modified.

    Parameters
    ----------
    name : str
        One of :data:`PRESETS`.
    seed : int
        Seed of every random draw.
    **overrides
        ``duration`` (s or ``"60s"``), ``rate`` (Hz or ``"1kHz"``), ``n_imus`` (int),
        ``outliers`` (bool: gyro outliers on/off, or a probability per sample and channel),
        ``chip_biases`` (gyro chip-to-chip bias sigma, rad/s or ``"0.1deg/s"``, or a dict
        per sensor type), ``noise_scale`` (multiplies every white-noise sigma),
        ``gyro_noise`` / ``accel_noise`` / ``mag_noise`` (sigma, SI or with units),
        ``t0_ns`` (first timestamp). ``None`` values are ignored.

    Raises
    ------
    UsageError
        Unknown preset or option, or invalid value (the message lists valid choices).
    """
    if name not in PRESETS:
        raise UsageError(f"unknown preset {name!r}; valid: {', '.join(sorted(PRESETS))}")
    n_imus = overrides.pop("n_imus", None)
    if n_imus is not None:
        if isinstance(n_imus, bool) or not isinstance(n_imus, (int, np.integer)) or n_imus < 1:
            raise UsageError(f"n_imus must be an integer >= 1, got {n_imus!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise UsageError(f"seed must be an integer >= 0, got {seed!r}")
    config = replace(_preset_base(name, None if n_imus is None else int(n_imus)), seed=int(seed))
    return apply_overrides(config, **overrides)


#: Options accepted by :func:`config_from_options` besides the preset overrides.
FREE_OPTIONS: Final[tuple[str, ...]] = ("imus", "motion", "motion_params", "seed")


def config_from_options(preset_name: str | None = None, **options: Any) -> SimConfig:
    """Validated SimConfig from CLI-style options (``None`` means "not given").

    With a preset name: the preset, modified by the options. Without: a co-aligned array
    of ``imus`` IMUs (default 16) with gyro and accelerometer at the origin, ``rate``
    (default 100 Hz), ``duration`` (default 10 s), ``motion`` (default ``static``; one of
    :data:`MOTIONS`) with ``motion_params`` (dict of strings, see :func:`make_motion`),
    white noise ``gyro_noise`` (default 0.15 deg/s) and ``accel_noise`` (default
    0.02 m/s^2), no outliers unless ``outliers`` is given.

    Options: ``imus``, ``rate``, ``duration``, ``motion``, ``motion_params``, ``seed``,
    ``outliers``, ``chip_biases``, ``noise_scale``, ``gyro_noise``, ``accel_noise``,
    ``mag_noise``, ``t0_ns``.

    Raises
    ------
    UsageError
        Naming the option and the valid choices.
    """
    valid = sorted({*FREE_OPTIONS, *PRESET_OVERRIDES} - {"n_imus"})
    for key in options:
        if key not in valid:
            raise UsageError(f"unknown simulation option {key!r}; valid: {', '.join(valid)}")
    given = {k: v for k, v in options.items() if v is not None}
    seed = given.pop("seed", 0)
    if isinstance(seed, str):
        try:
            seed = int(seed)
        except ValueError as err:
            raise UsageError(f"--seed must be an integer >= 0, got {seed!r}") from err
    imus = given.pop("imus", None)
    if imus is not None and (isinstance(imus, bool) or not isinstance(imus, (int, np.integer))):
        raise UsageError(f"--imus must be an integer >= 1, got {imus!r}")
    motion_name = given.pop("motion", None)
    motion_params = given.pop("motion_params", None) or {}
    if preset_name is not None:
        if preset_name not in PRESETS:
            raise UsageError(f"unknown preset {preset_name!r}; valid: {', '.join(sorted(PRESETS))}")
        config = preset(preset_name, seed=seed, n_imus=imus, **given)
        if motion_name is not None or motion_params:
            config = replace(
                config, motion=make_motion(motion_name or config.motion.NAME, **motion_params)
            )
        return config
    n_imus = 16 if imus is None else int(imus)
    if n_imus < 1:
        raise UsageError(f"--imus must be an integer >= 1, got {imus!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise UsageError(f"--seed must be an integer >= 0, got {seed!r}")
    has_mag = given.get("mag_noise") is not None
    sensors = ("gyro", "accel", "mag") if has_mag else ("gyro", "accel")
    config = SimConfig(
        array=ArrayConfig.co_aligned(n_imus, 100.0, sensors=sensors),
        duration_s=10.0,
        motion=make_motion(motion_name or "static", **motion_params),
        errors={"gyro": SensorErrors(noise=0.15 * _DEG), "accel": SensorErrors(noise=0.02)},
        seed=int(seed),
    )
    config = apply_overrides(config, **given)
    config.validate()
    return config
