"""The simulator: true triads of every IMU plus sensor errors, in fixed random-number chunks
(part of :mod:`imufdi_cli.simulate`; see its docstring for the seeding scheme).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Final

import numpy as np

from imufdi_cli.array import AXES, SENSOR_TYPES, ArrayConfig
from imufdi_cli.errors import UsageError
from imufdi_cli.log import ImuBlock, rechunk
from imufdi_cli.simulate.errors import SensorErrors, SimConfig
from imufdi_cli.simulate.motions import MotionState, rotation_from_rotvec

#: Samples per internal random-number chunk (fixed: results never depend on block_size).
CHUNK_SAMPLES: Final[int] = 4096


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
