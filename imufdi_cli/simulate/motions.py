"""Rigid-body motion profiles evaluated analytically at any sample time.

Rotation helpers, smooth scalar signals with exact derivatives, :class:`MotionState`, the
profiles of :data:`MOTIONS` and :func:`make_motion` (part of :mod:`imufdi_cli.simulate`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Final

import numpy as np

from imufdi_cli.errors import UnitError, UsageError
from imufdi_cli.units import STANDARD_GRAVITY, parse_quantity

#: Gravity in the navigation frame (z up), m/s^2.
GRAVITY_NAV: Final[np.ndarray] = np.array([0.0, 0.0, -STANDARD_GRAVITY])

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
