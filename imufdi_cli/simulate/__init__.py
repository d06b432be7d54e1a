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
:func:`preset` and :data:`PRESETS` (the reference scenarios of docs/simulate.md), and
:func:`config_from_options` (validated construction for the CLI).

Modules: :mod:`~imufdi_cli.simulate.motions` (rotations, motion profiles),
:mod:`~imufdi_cli.simulate.errors` (sensor errors, SimConfig),
:mod:`~imufdi_cli.simulate.run` (the simulator), :mod:`~imufdi_cli.simulate.presets`
(reference scenarios, CLI options). Everything public is re-exported here: import from
``imufdi_cli.simulate``. The MCAP writing is :func:`imufdi_cli.pipeline.simulate_file`.
"""

from __future__ import annotations

from imufdi_cli.simulate.errors import (
    DEFAULT_MAGNETIC_FIELD,
    DEFAULT_T0_NS,
    SensorErrors,
    SimConfig,
)
from imufdi_cli.simulate.motions import (
    GRAVITY_NAV,
    MOTIONS,
    AttitudeMotion,
    Motion,
    MotionState,
    StaticMotion,
    SwingMotion,
    TurntableMotion,
    VehicleMotion,
    euler_from_rotation,
    make_motion,
    rotation_from_euler,
    rotation_from_rotvec,
)
from imufdi_cli.simulate.presets import (
    CONE_HALF_ANGLE,
    FREE_OPTIONS,
    PRESET_OVERRIDES,
    PRESETS,
    PresetInfo,
    apply_overrides,
    config_from_options,
    conical_array,
    grid_positions,
    preset,
)
from imufdi_cli.simulate.run import (
    CHUNK_SAMPLES,
    simulate,
    simulate_block,
    true_block,
    true_motion,
)

__all__ = [
    "CHUNK_SAMPLES",
    "CONE_HALF_ANGLE",
    "DEFAULT_MAGNETIC_FIELD",
    "DEFAULT_T0_NS",
    "FREE_OPTIONS",
    "GRAVITY_NAV",
    "MOTIONS",
    "PRESETS",
    "PRESET_OVERRIDES",
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
