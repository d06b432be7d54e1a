"""What defines a simulated log: :class:`SensorErrors` per sensor type and :class:`SimConfig`
(part of :mod:`imufdi_cli.simulate`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Final

import numpy as np

from imufdi_cli.array import SENSOR_TYPES, ArrayConfig
from imufdi_cli.errors import UsageError
from imufdi_cli.simulate.motions import Motion, _json_ready

#: Default first timestamp: 1_700_000_000 s after the Unix epoch, in ns (looks like ROS time).
DEFAULT_T0_NS: Final[int] = 1_700_000_000 * 1_000_000_000
#: Default nav-frame magnetic field: 50 uT along [1/2, 0, sqrt(3)/2] (Berbra et al. h_m).
DEFAULT_MAGNETIC_FIELD: Final[tuple[float, float, float]] = (
    50e-6 * 0.5,
    0.0,
    50e-6 * math.sqrt(3.0) / 2.0,
)


# ==========================================================================================
# Sensor errors and the simulation config
# ==========================================================================================


@dataclass(frozen=True)
class SensorErrors:
    """Error model of one sensor type, applied to every axis of every IMU (SI units).

    The measurement of axis a of IMU k is
    ``(1 + s_ka) (M_k x_k)_a + b_a + c_ka + w_ka(t) + n_ka(t) + o_ka(t)``
    with x_k the true triad in the IMU frame.

    Attributes
    ----------
    noise : float
        White-noise standard deviation per sample n (rad/s, m/s^2 or T).
    bias : tuple of 3 floats
        Constant bias b common to all IMUs, per IMU-frame axis.
    chip_bias_sigma : float
        Standard deviation of constant chip-to-chip biases c, drawn once per IMU and axis.
    bias_random_walk : float
        Bias random walk w: standard deviation of its increment over one second
        (SI per sqrt(s)); per sample the increment has std ``bias_random_walk / sqrt(rate)``.
    scale_factor_sigma : float
        Standard deviation of the scale-factor errors s (dimensionless, 1e-3 = 1000 ppm),
        drawn once per IMU and axis.
    misalignment_sigma : float
        Standard deviation (rad) of the small rotation vector of each IMU's sensor triad
        (``M_k = exp([delta_k]x)``), drawn once per IMU.
    outlier_probability : float
        Probability per sample and channel of an outlier o.
    outlier_amplitude : float
        Outlier size; its sign is random (+-amplitude).
    """

    noise: float = 0.0
    bias: tuple[float, float, float] = (0.0, 0.0, 0.0)
    chip_bias_sigma: float = 0.0
    bias_random_walk: float = 0.0
    scale_factor_sigma: float = 0.0
    misalignment_sigma: float = 0.0
    outlier_probability: float = 0.0
    outlier_amplitude: float = 0.0

    def validate(self, sensor_type: str) -> None:
        """Raise UsageError if a value is out of range."""
        for name in (
            "noise",
            "chip_bias_sigma",
            "bias_random_walk",
            "scale_factor_sigma",
            "misalignment_sigma",
            "outlier_amplitude",
        ):
            value = float(getattr(self, name))
            if not (math.isfinite(value) and value >= 0):
                raise UsageError(f"{sensor_type} {name} must be >= 0, got {value!r}")
        if not 0.0 <= self.outlier_probability <= 1.0:
            raise UsageError(
                f"{sensor_type} outlier probability must be in [0, 1], "
                f"got {self.outlier_probability!r}"
            )
        if len(self.bias) != 3 or not all(math.isfinite(float(b)) for b in self.bias):
            raise UsageError(f"{sensor_type} bias must be 3 finite numbers")


@dataclass(frozen=True)
class SimConfig:
    """Everything that defines a simulated log.

    Attributes
    ----------
    array : ArrayConfig
        Geometry, sample rate (``array.rate_hz``) and nominal noise.
    duration_s : float
        Log length, s; ``n_samples = round(duration_s * rate_hz)``.
    motion : Motion
        Rigid-body motion profile.
    errors : dict
        Sensor type -> :class:`SensorErrors` (types missing: error-free).
    seed : int
        Seed of every random draw.
    t0_ns : int
        Timestamp of the first sample, ns; sample i is at ``t0_ns + round(i * 1e9 / rate)``.
    magnetic_field : tuple of 3 floats
        Nav-frame magnetic field h_n, tesla.
    name : str
        Preset name, or ``"custom"``.
    """

    array: ArrayConfig
    duration_s: float
    motion: Motion
    errors: Mapping[str, SensorErrors] = field(default_factory=dict)
    seed: int = 0
    t0_ns: int = DEFAULT_T0_NS
    magnetic_field: tuple[float, float, float] = DEFAULT_MAGNETIC_FIELD
    name: str = "custom"

    @property
    def rate_hz(self) -> float:
        return float(self.array.rate_hz)

    @property
    def n_samples(self) -> int:
        return round(self.duration_s * self.rate_hz)

    def validate(self) -> None:
        """Raise UsageError when the config cannot be simulated."""
        if not (math.isfinite(self.duration_s) and self.duration_s > 0):
            raise UsageError(f"duration must be > 0 s, got {self.duration_s!r}")
        if self.n_samples < 1:
            raise UsageError(f"duration {self.duration_s} s at {self.rate_hz} Hz gives no sample")
        if not isinstance(self.seed, (int, np.integer)) or self.seed < 0:
            raise UsageError(f"seed must be an integer >= 0, got {self.seed!r}")
        for sensor_type, errors in self.errors.items():
            if sensor_type not in SENSOR_TYPES:
                raise UsageError(
                    f"unknown sensor type {sensor_type!r} in errors; valid: "
                    + ", ".join(SENSOR_TYPES)
                )
            errors.validate(sensor_type)

    def timestamps(self, start: int, stop: int) -> np.ndarray:
        """Timestamps (ns, int64) of samples ``start:stop``."""
        index = np.arange(start, stop, dtype=np.float64)
        return self.t0_ns + np.round(index * 1e9 / self.rate_hz).astype(np.int64)

    def describe(self) -> dict[str, Any]:
        """JSON-ready description (for MCAP metadata)."""
        return {
            "name": self.name,
            "duration_s": self.duration_s,
            "rate_hz": self.rate_hz,
            "seed": int(self.seed),
            "t0_ns": int(self.t0_ns),
            "magnetic_field_T": list(self.magnetic_field),
            **self.motion.describe(),
            "errors": {
                k: {f: _json_ready(v) for f, v in e.__dict__.items()}
                for k, e in self.errors.items()
            },
        }
