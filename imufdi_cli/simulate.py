"""Simulated redundant IMU arrays: rigid-body motion, sensor errors, reference presets.

The simulator evaluates a rigid-body motion analytically at every sample time (so any
sample can be computed without the ones before it), projects it onto every IMU of an
:class:`~imufdi_cli.array.ArrayConfig` and adds sensor errors:

- body angular rate ``w`` (rad/s), angular acceleration ``dw/dt`` (rad/s^2), specific force
  at the body origin ``f`` (m/s^2, body frame, gravity included: a level body at rest
  measures ``+9.80665`` on z), attitude ``C_nb`` (body -> navigation frame, nav z up);
- gyro of IMU k: ``R_k^T w``; accelerometer: ``R_k^T (f + dw/dt x r_k + w x (w x r_k))``
  (rigid-body lever arm, r_k the IMU position); magnetometer: ``R_k^T C_nb^T h_n``;
- errors per sensor axis: white noise, constant bias (common and chip-to-chip), bias
  random walk, scale factor, misalignment (small rotation per IMU), outliers.

Random numbers are drawn per internal chunk of :data:`CHUNK_SAMPLES` samples from a
generator keyed by ``(seed, chunk index, sensor type, error component)`` through
:class:`numpy.random.SeedSequence`, so a log is bit-identical whatever ``block_size`` the
caller streams it with, and turning one error off does not change the others.

Public entry points: :func:`simulate` (streaming), :func:`simulate_block` (in memory),
:func:`preset` and :data:`PRESETS` (the reference scenarios of DESIGN.md §8), and
:func:`config_from_options` (validated construction for the CLI).
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, ClassVar, Final

import numpy as np

from imufdi_cli.array import AXES, SENSOR_TYPES, ArrayConfig, ImuSpec
from imufdi_cli.errors import UnitError, UsageError
from imufdi_cli.log import ImuBlock, rechunk
from imufdi_cli.units import STANDARD_GRAVITY, parse_quantity, sensor_dimension

#: Default first timestamp: 1_700_000_000 s after the Unix epoch, in ns (looks like ROS time).
DEFAULT_T0_NS: Final[int] = 1_700_000_000 * 1_000_000_000
#: Samples per internal random-number chunk (fixed: results never depend on block_size).
CHUNK_SAMPLES: Final[int] = 4096
#: Gravity in the navigation frame (z up), m/s^2.
GRAVITY_NAV: Final[np.ndarray] = np.array([0.0, 0.0, -STANDARD_GRAVITY])
#: Default nav-frame magnetic field: 50 uT along [1/2, 0, sqrt(3)/2] (Berbra et al. h_m).
DEFAULT_MAGNETIC_FIELD: Final[tuple[float, float, float]] = (
    50e-6 * 0.5,
    0.0,
    50e-6 * math.sqrt(3.0) / 2.0,
)

_DEG = math.pi / 180.0


# ==========================================================================================
# Rotation helpers (vectorised)
# ==========================================================================================


def _skew(vectors: np.ndarray) -> np.ndarray:
    """Cross-product matrices [v]x, shape (..., 3, 3), of vectors (..., 3)."""
    x, y, z = vectors[..., 0], vectors[..., 1], vectors[..., 2]
    zero = np.zeros_like(x)
    return np.stack(
        [
            np.stack([zero, -z, y], axis=-1),
            np.stack([z, zero, -x], axis=-1),
            np.stack([-y, x, zero], axis=-1),
        ],
        axis=-2,
    )


def rotation_from_rotvec(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrices exp([v]x), shape (..., 3, 3), of rotation vectors (..., 3) in rad.

    Rodrigues' formula; exact for any angle (series used near zero).
    """
    rotvec = np.asarray(rotvec, dtype=float)
    angle = np.linalg.norm(rotvec, axis=-1)[..., None, None]
    small = angle < 1e-6
    safe = np.where(small, 1.0, angle)
    sin_term = np.where(small, 1.0 - angle**2 / 6.0, np.sin(safe) / safe)
    cos_term = np.where(small, 0.5 - angle**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    k = _skew(rotvec)
    return np.eye(3) + sin_term * k + cos_term * (k @ k)


def rotation_from_euler(roll: Any, pitch: Any, yaw: Any) -> np.ndarray:
    """Body -> nav rotation ``C_nb = Rz(yaw) Ry(pitch) Rx(roll)`` (ZYX Euler angles, rad).

    Inputs broadcast together; output shape (..., 3, 3).
    """
    roll, pitch, yaw = np.broadcast_arrays(
        np.asarray(roll, float), np.asarray(pitch, float), np.asarray(yaw, float)
    )
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cy, sy = np.cos(yaw), np.sin(yaw)
    return np.stack(
        [
            np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], axis=-1),
            np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], axis=-1),
            np.stack([-sp, cp * sr, cp * cr], axis=-1),
        ],
        axis=-2,
    )


def euler_from_rotation(matrix: np.ndarray) -> np.ndarray:
    """ZYX Euler angles ``[roll, pitch, yaw]`` (rad), shape (..., 3), of C_nb (..., 3, 3)."""
    matrix = np.asarray(matrix, dtype=float)
    roll = np.arctan2(matrix[..., 2, 1], matrix[..., 2, 2])
    pitch = -np.arcsin(np.clip(matrix[..., 2, 0], -1.0, 1.0))
    yaw = np.arctan2(matrix[..., 1, 0], matrix[..., 0, 0])
    return np.stack([roll, pitch, yaw], axis=-1)


def _euler_body_rates(
    angles: np.ndarray, rates: np.ndarray, accels: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Body angular rate and acceleration from ZYX Euler angles and their derivatives.

    ``p = dphi - dpsi sin(theta)``, ``q = dtheta cos(phi) + dpsi cos(theta) sin(phi)``,
    ``r = -dtheta sin(phi) + dpsi cos(theta) cos(phi)`` (Titterton & Weston, Strapdown
    Inertial Navigation Technology, eq. 3.60 inverted), and their exact time derivatives.
    All arrays (N, 3) ordered (roll, pitch, yaw); outputs (N, 3) rad/s and rad/s^2.
    """
    phi, theta = angles[:, 0], angles[:, 1]
    d_phi, d_theta, d_psi = rates[:, 0], rates[:, 1], rates[:, 2]
    dd_phi, dd_theta, dd_psi = accels[:, 0], accels[:, 1], accels[:, 2]
    s_phi, c_phi = np.sin(phi), np.cos(phi)
    s_theta, c_theta = np.sin(theta), np.cos(theta)
    p = d_phi - d_psi * s_theta
    q = d_theta * c_phi + d_psi * c_theta * s_phi
    r = -d_theta * s_phi + d_psi * c_theta * c_phi
    dp = dd_phi - dd_psi * s_theta - d_psi * d_theta * c_theta
    dq = (
        dd_theta * c_phi
        - d_theta * d_phi * s_phi
        + dd_psi * c_theta * s_phi
        - d_psi * d_theta * s_theta * s_phi
        + d_psi * d_phi * c_theta * c_phi
    )
    dr = (
        -dd_theta * s_phi
        - d_theta * d_phi * c_phi
        + dd_psi * c_theta * c_phi
        - d_psi * d_theta * s_theta * c_phi
        - d_psi * d_phi * c_theta * s_phi
    )
    return np.stack([p, q, r], axis=-1), np.stack([dp, dq, dr], axis=-1)


# ==========================================================================================
# Smooth scalar signals with exact first and second derivatives
# ==========================================================================================


def _sinusoid(
    t: np.ndarray, amplitude: float, frequency_hz: float, phase: float = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``A sin(2 pi f t + phase)`` and its first two derivatives."""
    omega = 2.0 * math.pi * frequency_hz
    arg = omega * t + phase
    s, c = np.sin(arg), np.cos(arg)
    return amplitude * s, amplitude * omega * c, -amplitude * omega**2 * s


def _smoothstep(
    t: np.ndarray, start: float, duration: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Quintic (minimum-jerk) step 0 -> 1 over ``[start, start + duration]``.

    ``s(u) = 10u^3 - 15u^4 + 6u^5``: zero rate and acceleration at both ends, so motions
    built from it have continuous angular rate and angular acceleration.
    """
    if duration <= 0:
        step = (t >= start).astype(float)
        return step, np.zeros_like(t), np.zeros_like(t)
    u = np.clip((t - start) / duration, 0.0, 1.0)
    inside = (t > start) & (t < start + duration)
    value = u**3 * (10.0 - 15.0 * u + 6.0 * u**2)
    rate = np.where(inside, 30.0 * u**2 * (1.0 - u) ** 2 / duration, 0.0)
    accel = np.where(inside, 60.0 * u * (1.0 - u) * (1.0 - 2.0 * u) / duration**2, 0.0)
    return value, rate, accel


def _product(
    a: tuple[np.ndarray, np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray, np.ndarray]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Product of two signals with derivatives (Leibniz rule)."""
    return (
        a[0] * b[0],
        a[1] * b[0] + a[0] * b[1],
        a[2] * b[0] + 2.0 * a[1] * b[1] + a[0] * b[2],
    )


# ==========================================================================================
# Motion profiles
# ==========================================================================================


@dataclass
class MotionState:
    """Rigid-body motion of the array body frame at N sample times.

    Attributes
    ----------
    t_s : ndarray, shape (N,)
        Sample times, s.
    angular_rate : ndarray, shape (N, 3)
        Body angular rate w (body frame), rad/s.
    angular_acceleration : ndarray, shape (N, 3)
        dw/dt (body frame), rad/s^2.
    specific_force : ndarray, shape (N, 3)
        Specific force at the body origin, body frame, m/s^2 (``C_nb^T (a_n - g_n)``).
    attitude : ndarray, shape (N, 3, 3)
        C_nb, body -> navigation frame (nav z up).
    velocity : ndarray, shape (N, 3)
        Velocity of the body origin in the navigation frame, m/s (for consistency checks:
        its derivative is ``C_nb f + g_n``).
    """

    t_s: np.ndarray
    angular_rate: np.ndarray
    angular_acceleration: np.ndarray
    specific_force: np.ndarray
    attitude: np.ndarray
    velocity: np.ndarray


def _vector3(value: Any, dimension: str, name: str) -> np.ndarray:
    """A 3-vector from a quantity, a ``"a,b,c"`` string or a sequence of quantities (SI)."""
    if isinstance(value, str):
        parts = [p for p in value.split(",")]
        if len(parts) == 1:
            return np.full(3, parse_quantity(parts[0], dimension, name=name))
        items: Sequence[Any] = parts
    elif isinstance(value, (int, float)):
        return np.full(3, float(value))
    else:
        items = list(value)
    if len(items) != 3:
        raise UsageError(f"{name}: expected 3 components (x, y, z), got {len(items)}")
    return np.array([parse_quantity(v, dimension, name=name) for v in items], dtype=float)


def _json_ready(value: Any) -> Any:
    """Tuples, arrays and numpy scalars -> lists and floats (nested)."""
    if isinstance(value, (tuple, list, np.ndarray)):
        return [_json_ready(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


class Motion:
    """Base class of motion profiles: ``evaluate(t_s) -> MotionState``.

    Subclasses are frozen dataclasses whose fields are the profile's parameters (SI).
    """

    NAME: ClassVar[str] = ""

    def evaluate(self, t_s: np.ndarray) -> MotionState:  # pragma: no cover - abstract
        raise NotImplementedError

    def describe(self) -> dict[str, Any]:
        """Name and parameters as JSON-ready values."""
        return {"motion": self.NAME, **{k: _json_ready(v) for k, v in self.__dict__.items()}}


class _EulerMotion(Motion):
    """Attitude given by ZYX Euler angle signals; body origin acceleration from a hook."""

    def _euler(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        raise NotImplementedError  # pragma: no cover

    def _origin_motion(
        self, t: np.ndarray, attitude: np.ndarray, rate: np.ndarray, accel: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """(acceleration, velocity) of the body origin in the nav frame; default at rest."""
        zeros = np.zeros((t.shape[0], 3))
        return zeros, zeros.copy()

    def evaluate(self, t_s: np.ndarray) -> MotionState:
        t = np.asarray(t_s, dtype=float)
        angles, angle_rates, angle_accels = self._euler(t)
        attitude = rotation_from_euler(angles[:, 0], angles[:, 1], angles[:, 2])
        rate, accel = _euler_body_rates(angles, angle_rates, angle_accels)
        accel_nav, velocity_nav = self._origin_motion(t, attitude, rate, accel)
        specific_force = np.einsum("nji,nj->ni", attitude, accel_nav - GRAVITY_NAV)
        return MotionState(t, rate, accel, specific_force, attitude, velocity_nav)


@dataclass(frozen=True)
class StaticMotion(_EulerMotion):
    """The body at rest at a fixed attitude ``(roll, pitch, yaw)`` in rad."""

    NAME: ClassVar[str] = "static"
    attitude_rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def _euler(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        angles = np.broadcast_to(np.asarray(self.attitude_rpy, float), (t.shape[0], 3))
        return angles.copy(), np.zeros((t.shape[0], 3)), np.zeros((t.shape[0], 3))


@dataclass(frozen=True)
class TurntableMotion(Motion):
    """Constant body angular rate (vector, rad/s) about a fixed point at the body origin.

    ``C_nb(t) = C_nb(0) exp(t [w]x)`` exactly (constant body rate), starting level.
    """

    NAME: ClassVar[str] = "turntable"
    rate: tuple[float, float, float] = (10 * _DEG, 10 * _DEG, 10 * _DEG)

    def evaluate(self, t_s: np.ndarray) -> MotionState:
        t = np.asarray(t_s, dtype=float)
        rate = np.asarray(self.rate, dtype=float)
        attitude = rotation_from_rotvec(t[:, None] * rate[None, :])
        n = t.shape[0]
        specific_force = np.einsum("nji,j->ni", attitude, -GRAVITY_NAV)
        return MotionState(
            t,
            np.broadcast_to(rate, (n, 3)).copy(),
            np.zeros((n, 3)),
            specific_force,
            attitude,
            np.zeros((n, 3)),
        )


@dataclass(frozen=True)
class SwingMotion(_EulerMotion):
    """Pendulum-like swinging about a fixed pivot (a limb, a hanging board).

    Euler angles ``angle_i(t) = env(t) * amplitude_i * sin(2 pi frequency_i t + phase_i)``
    (roll, pitch, yaw), where ``env`` is a quintic ramp from 0 to 1 over
    ``[start, start + ramp]`` (the body is at rest before ``start``). The body origin is at
    ``pivot_offset`` (body frame, m) from the fixed pivot, so its nav-frame acceleration is
    ``C_nb (dw/dt x r + w x (w x r))``; a zero offset rotates about the origin.
    """

    NAME: ClassVar[str] = "swing"
    amplitude: tuple[float, float, float] = (30 * _DEG, 10 * _DEG, 5 * _DEG)
    frequency_hz: tuple[float, float, float] = (1.0, 0.7, 0.4)
    phase: tuple[float, float, float] = (0.0, 0.5, 1.0)
    pivot_offset: tuple[float, float, float] = (0.0, 0.0, -0.3)
    start: float = 0.0
    ramp: float = 1.0

    def _euler(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        envelope = _smoothstep(t, self.start, self.ramp)
        columns = [
            _product(envelope, _sinusoid(t, a, f, p))
            for a, f, p in zip(self.amplitude, self.frequency_hz, self.phase)
        ]
        return tuple(np.stack([c[i] for c in columns], axis=-1) for i in range(3))  # type: ignore[return-value]

    def _origin_motion(
        self, t: np.ndarray, attitude: np.ndarray, rate: np.ndarray, accel: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        offset = np.asarray(self.pivot_offset, dtype=float)
        accel_body = np.cross(accel, offset) + np.cross(rate, np.cross(rate, offset))
        velocity_body = np.cross(rate, offset)
        return (
            np.einsum("nij,nj->ni", attitude, accel_body),
            np.einsum("nij,nj->ni", attitude, velocity_body),
        )


@dataclass(frozen=True)
class VehicleMotion(_EulerMotion):
    """Ground vehicle driving: speed changes, alternating turns, body vibration.

    Speed ``v(t) = speed + speed_variation sin(2 pi t / speed_period)`` along the heading;
    yaw rate ``turn_rate sin(2 pi t / turn_period)`` (alternating left and right turns);
    roll and pitch vibrate with amplitude ``vibration_angle`` at ``vibration_hz`` (and
    0.77 of it); the body bounces vertically with acceleration amplitude
    ``vibration_accel`` at ``vibration_hz``. Nav-frame acceleration
    ``a = dv/dt u(psi) + v dpsi/dt u(psi + 90deg) + [0, 0, z'']``.
    """

    NAME: ClassVar[str] = "vehicle"
    speed: float = 10.0
    speed_variation: float = 3.0
    speed_period: float = 20.0
    turn_rate: float = 15 * _DEG
    turn_period: float = 12.0
    vibration_hz: float = 12.0
    vibration_angle: float = 0.3 * _DEG
    vibration_accel: float = 0.5

    def _euler(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        roll = _sinusoid(t, self.vibration_angle, self.vibration_hz)
        pitch = _sinusoid(t, self.vibration_angle, 0.77 * self.vibration_hz, 1.3)
        # yaw rate A sin(w t)  ->  yaw = A/w (1 - cos(w t)), starts at 0
        w_turn = 2.0 * math.pi / self.turn_period
        yaw = (
            self.turn_rate / w_turn * (1.0 - np.cos(w_turn * t)),
            self.turn_rate * np.sin(w_turn * t),
            self.turn_rate * w_turn * np.cos(w_turn * t),
        )
        return tuple(np.stack([roll[i], pitch[i], yaw[i]], axis=-1) for i in range(3))  # type: ignore[return-value]

    def _origin_motion(
        self, t: np.ndarray, attitude: np.ndarray, rate: np.ndarray, accel: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        speed, speed_dot, _ = _sinusoid(t, self.speed_variation, 1.0 / self.speed_period)
        speed = speed + self.speed
        yaw, yaw_rate, _ = (c[:, 2] for c in self._euler(t))
        heading = np.stack([np.cos(yaw), np.sin(yaw), np.zeros_like(yaw)], axis=-1)
        normal = np.stack([-np.sin(yaw), np.cos(yaw), np.zeros_like(yaw)], axis=-1)
        # vertical bounce: z'' = A sin(w t)  ->  z' = -A/w cos(w t)
        w_vib = 2.0 * math.pi * self.vibration_hz
        bounce_accel = self.vibration_accel * np.sin(w_vib * t)
        bounce_velocity = -self.vibration_accel / w_vib * np.cos(w_vib * t)
        up = np.array([0.0, 0.0, 1.0])
        accel_nav = (
            speed_dot[:, None] * heading
            + (speed * yaw_rate)[:, None] * normal
            + bounce_accel[:, None] * up
        )
        velocity_nav = speed[:, None] * heading + bounce_velocity[:, None] * up
        return accel_nav, velocity_nav


@dataclass(frozen=True)
class AttitudeMotion(_EulerMotion):
    """Smooth manoeuvres between attitude set points, body origin at rest (hover).

    Starts at ``initial_rpy`` (roll, pitch, yaw in rad); each move
    ``(start_s, duration_s, (roll, pitch, yaw))`` goes to the new set point along a quintic
    (minimum-jerk) path of every Euler angle, with zero rate and angular acceleration at both
    ends. Moves must not overlap.
    """

    NAME: ClassVar[str] = "attitude"
    initial_rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)
    moves: tuple[tuple[float, float, tuple[float, float, float]], ...] = (
        (1.0, 1.0, (20 * _DEG, -10 * _DEG, 30 * _DEG)),
    )

    def set_points(self) -> list[tuple[float, np.ndarray]]:
        """``(time reached, rpy)`` of the initial attitude and of every move's end."""
        points = [(0.0, np.asarray(self.initial_rpy, float))]
        for start, duration, target in self.moves:
            points.append((start + duration, np.asarray(target, float)))
        return points

    def _euler(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        previous = np.asarray(self.initial_rpy, float)
        angles = np.broadcast_to(previous, (t.shape[0], 3)).copy()
        rates = np.zeros((t.shape[0], 3))
        accels = np.zeros((t.shape[0], 3))
        for start, duration, target in self.moves:
            delta = np.asarray(target, float) - previous
            step, step_rate, step_accel = _smoothstep(t, start, duration)
            angles += step[:, None] * delta
            rates += step_rate[:, None] * delta
            accels += step_accel[:, None] * delta
            previous = np.asarray(target, float)
        return angles, rates, accels


MOTIONS: Final[dict[str, type[Motion]]] = {
    cls.NAME: cls
    for cls in (StaticMotion, TurntableMotion, SwingMotion, VehicleMotion, AttitudeMotion)
}

# parameter name -> (dimension, vector?) for construction from strings
_MOTION_PARAMS: Final[dict[str, dict[str, tuple[str, bool]]]] = {
    "static": {"attitude_rpy": ("angle", True)},
    "turntable": {"rate": ("angular_rate", True)},
    "swing": {
        "amplitude": ("angle", True),
        "frequency_hz": ("frequency", True),
        "phase": ("angle", True),
        "pivot_offset": ("length", True),
        "start": ("time", False),
        "ramp": ("time", False),
    },
    "vehicle": {
        "speed": ("dimensionless", False),
        "speed_variation": ("dimensionless", False),
        "speed_period": ("time", False),
        "turn_rate": ("angular_rate", False),
        "turn_period": ("time", False),
        "vibration_hz": ("frequency", False),
        "vibration_angle": ("angle", False),
        "vibration_accel": ("acceleration", False),
    },
    "attitude": {"initial_rpy": ("angle", True)},
}


def make_motion(name: str, **params: Any) -> Motion:
    """Build a motion profile by name; parameter values may be quantity strings.

    Vector parameters accept ``"10deg/s"`` (same on x, y, z), ``"10deg/s,0,5deg/s"`` or a
    sequence. Vehicle speeds are in m/s (numbers). Raises UsageError naming valid choices.
    """
    if name not in MOTIONS:
        raise UsageError(f"unknown motion {name!r}; valid: {', '.join(sorted(MOTIONS))}")
    spec = _MOTION_PARAMS[name]
    values: dict[str, Any] = {}
    for key, raw in params.items():
        if name == "attitude" and key == "moves":
            values[key] = tuple(
                (float(s), float(d), tuple(float(a) for a in rpy)) for s, d, rpy in raw
            )
            continue
        if key not in spec:
            valid = sorted(spec) + (["moves"] if name == "attitude" else [])
            raise UsageError(f"motion {name}: unknown parameter {key!r}; valid: {', '.join(valid)}")
        dimension, is_vector = spec[key]
        try:
            if is_vector:
                values[key] = tuple(float(v) for v in _vector3(raw, dimension, key))
            else:
                values[key] = parse_quantity(raw, dimension, name=key)
        except UnitError as err:
            raise UsageError(f"motion {name}: {err}") from err
    return MOTIONS[name](**values)


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


# ==========================================================================================
# The simulator
# ==========================================================================================

_COMPONENT_NOISE, _COMPONENT_WALK, _COMPONENT_OUTLIER = 0, 1, 2


@dataclass
class _StaticErrors:
    """Per-log constant error draws of one sensor type."""

    scale: np.ndarray  # (m, 3)
    misalignment: np.ndarray  # (m, 3, 3)
    bias: np.ndarray  # (m, 3)
    present: np.ndarray  # (m, 3) bool


def _draw_static_errors(config: SimConfig) -> dict[str, _StaticErrors]:
    m = config.array.n_imus
    result: dict[str, _StaticErrors] = {}
    for type_index, sensor_type in enumerate(SENSOR_TYPES):
        if not config.array.has(sensor_type):
            continue
        errors = config.errors.get(sensor_type, SensorErrors())
        rng = np.random.default_rng(np.random.SeedSequence(config.seed, spawn_key=(0, type_index)))
        # always draw in the same order so one option does not shift the others' draws
        scale_draw = rng.standard_normal((m, 3))
        misalignment_draw = rng.standard_normal((m, 3))
        chip_bias_draw = rng.standard_normal((m, 3))
        present = np.array(
            [[axis in imu.axes_of(sensor_type) for axis in AXES] for imu in config.array.imus]
        )
        result[sensor_type] = _StaticErrors(
            scale=errors.scale_factor_sigma * scale_draw,
            misalignment=rotation_from_rotvec(errors.misalignment_sigma * misalignment_draw),
            bias=np.asarray(errors.bias, float)[None, :] + errors.chip_bias_sigma * chip_bias_draw,
            present=present,
        )
    return result


def _to_imu_frames(rotations: np.ndarray, body: np.ndarray) -> np.ndarray:
    """``R_k^T x`` for every sample and IMU: rotations (m, 3, 3), body (N, m or 1, 3) ->
    (N, m, 3). Batched matmul over IMUs (row vectors times R_k)."""
    body_per_imu = np.broadcast_to(body, (body.shape[0], rotations.shape[0], 3))
    return np.ascontiguousarray(np.swapaxes(np.swapaxes(body_per_imu, 0, 1) @ rotations, 0, 1))


def _true_triads(config: SimConfig, state: MotionState) -> dict[str, np.ndarray]:
    """Error-free triads (N, m, 3) in each IMU's frame for every sensor type present."""
    rotations = config.array.rotations()  # (m, 3, 3) IMU -> body
    triads: dict[str, np.ndarray] = {}
    if config.array.has("gyro"):
        triads["gyro"] = _to_imu_frames(rotations, state.angular_rate[:, None, :])
    if config.array.has("accel"):
        positions = config.array.positions()  # (m, 3)
        w = state.angular_rate[:, None, :]
        lever = np.cross(state.angular_acceleration[:, None, :], positions[None]) + np.cross(
            w, np.cross(w, positions[None])
        )
        accel_body = state.specific_force[:, None, :] + lever  # (N, m, 3)
        triads["accel"] = _to_imu_frames(rotations, accel_body)
    if config.array.has("mag"):
        field_body = np.einsum(
            "nji,j->ni", state.attitude, np.asarray(config.magnetic_field, float)
        )
        triads["mag"] = _to_imu_frames(rotations, field_body[:, None, :])
    return triads


def _simulate_chunks(config: SimConfig) -> Iterator[ImuBlock]:
    """Fixed-length internal chunks; random draws keyed by chunk index."""
    config.validate()
    static = _draw_static_errors(config)
    n_total = config.n_samples
    m = config.array.n_imus
    walk_state = {s: np.zeros((m, 3)) for s in static}
    for chunk_index, start in enumerate(range(0, n_total, CHUNK_SAMPLES)):
        stop = min(start + CHUNK_SAMPLES, n_total)
        n = stop - start
        t_s = np.arange(start, stop, dtype=np.float64) / config.rate_hz
        state = config.motion.evaluate(t_s)
        triads = _true_triads(config, state)
        out: dict[str, np.ndarray | None] = {s: None for s in SENSOR_TYPES}
        for sensor_type, true in triads.items():
            type_index = SENSOR_TYPES.index(sensor_type)
            errors = config.errors.get(sensor_type, SensorErrors())
            fixed = static[sensor_type]

            def generator(
                component: int, _t: int = type_index, _c: int = chunk_index
            ) -> np.random.Generator:
                key = (1, _c, _t, component)
                return np.random.default_rng(np.random.SeedSequence(config.seed, spawn_key=key))

            # M_k x: rows of x times M_k^T, batched over IMUs
            measured = _to_imu_frames(np.swapaxes(fixed.misalignment, 1, 2), true)
            measured *= 1.0 + fixed.scale[None]
            measured += fixed.bias[None]
            if errors.bias_random_walk > 0:
                step_sigma = errors.bias_random_walk / math.sqrt(config.rate_hz)
                steps = step_sigma * generator(_COMPONENT_WALK).standard_normal((n, m, 3))
                walk = walk_state[sensor_type][None] + np.cumsum(steps, axis=0)
                walk_state[sensor_type] = walk[-1].copy()
                measured += walk
            if errors.noise > 0:
                measured += errors.noise * generator(_COMPONENT_NOISE).standard_normal((n, m, 3))
            if errors.outlier_probability > 0 and errors.outlier_amplitude > 0:
                # one uniform draw gives both the event (u < p) and its sign (u < p/2 -> -)
                uniform = generator(_COMPONENT_OUTLIER).random((n, m, 3))
                p = errors.outlier_probability
                outliers = np.where(uniform < 0.5 * p, -1.0, np.where(uniform < p, 1.0, 0.0))
                measured += errors.outlier_amplitude * outliers
            measured[:, ~fixed.present] = np.nan
            out[sensor_type] = measured
        yield ImuBlock(t_ns=config.timestamps(start, stop), **out)


def simulate(
    config: SimConfig, *, block_size: int = 10_000
) -> tuple[ArrayConfig, Iterator[ImuBlock]]:
    """Stream a simulated log in blocks of ``block_size`` samples (last may be shorter).

    Parameters
    ----------
    config : SimConfig
        What to simulate.
    block_size : int
        Samples per yielded block; the data do not depend on it.

    Returns
    -------
    array : ArrayConfig
        The array geometry (with nominal noise), to embed in the log.
    blocks : iterator of ImuBlock
        Triads (N, m, 3) in SI, IMU frames; axes an IMU does not have are NaN; sensor types
        absent from the array are None. Memory stays bounded by the block and chunk sizes.

    Raises
    ------
    UsageError
        Invalid config or block size (raised at call time, not on iteration).
    """
    if not isinstance(block_size, (int, np.integer)) or block_size < 1:
        raise UsageError(f"block_size must be an integer >= 1, got {block_size!r}")
    config.validate()
    return config.array, rechunk(_simulate_chunks(config), int(block_size))


def simulate_block(config: SimConfig) -> tuple[ArrayConfig, ImuBlock]:
    """The whole simulated log as one in-memory :class:`ImuBlock` (see :func:`simulate`)."""
    config.validate()
    return config.array, ImuBlock.concatenate(_simulate_chunks(config))


def true_motion(config: SimConfig, start: int = 0, stop: int | None = None) -> MotionState:
    """Error-free motion of samples ``start:stop`` (for checks and plots)."""
    stop = config.n_samples if stop is None else stop
    return config.motion.evaluate(np.arange(start, stop, dtype=np.float64) / config.rate_hz)


def true_block(config: SimConfig, start: int = 0, stop: int | None = None) -> ImuBlock:
    """Error-free triads of samples ``start:stop`` (absent axes NaN, as in the log)."""
    stop = config.n_samples if stop is None else stop
    triads = _true_triads(config, true_motion(config, start, stop))
    for sensor_type, values in triads.items():
        present = np.array(
            [[a in imu.axes_of(sensor_type) for a in AXES] for imu in config.array.imus]
        )
        values[:, ~present] = np.nan
    return ImuBlock(t_ns=config.timestamps(start, stop), **triads)


# ==========================================================================================
# Presets (DESIGN.md §8)
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


def _preset_base(name: str, n_imus: int | None) -> SimConfig:
    if name == "paper-table4":
        n = 16 if n_imus is None else n_imus
        array = ArrayConfig.co_aligned(n, 100.0, sensors=("gyro", "accel"))
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
            name=name,
        )
    if name == "conical6":
        n = 6 if n_imus is None else n_imus
        return SimConfig(
            array=conical_array(n, 100.0),
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
            name=name,
        )
    if name == "wearable12":
        n = 12 if n_imus is None else n_imus
        array = ArrayConfig.co_aligned(
            n, 100.0, sensors=("gyro", "accel"), positions=grid_positions(n)
        )
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
            name=name,
        )
    if name == "quadrotor-marg":
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
            name=name,
        )
    raise UsageError(f"unknown preset {name!r}; valid: {', '.join(sorted(PRESETS))}")


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
    """The SimConfig of a reference scenario (DESIGN.md §8), optionally modified.

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


__all__ = [
    "CHUNK_SAMPLES",
    "CONE_HALF_ANGLE",
    "DEFAULT_MAGNETIC_FIELD",
    "DEFAULT_T0_NS",
    "MOTIONS",
    "PRESETS",
    "AttitudeMotion",
    "Motion",
    "MotionState",
    "PresetInfo",
    "SensorErrors",
    "SimConfig",
    "StaticMotion",
    "SwingMotion",
    "TurntableMotion",
    "VehicleMotion",
    "apply_overrides",
    "config_from_options",
    "conical_array",
    "euler_from_rotation",
    "grid_positions",
    "make_motion",
    "preset",
    "rotation_from_euler",
    "rotation_from_rotvec",
    "simulate",
    "simulate_block",
    "true_block",
    "true_motion",
]
