"""Per-IMU vectors in the body frame, for the firmware-style consistency detectors.

Flight-controller firmware (PX4's EKF2 selector, ArduPilot's pre-arm checks) compares whole
IMUs: the 3-vector of one IMU against the array mean or against the primary IMU, each
already rotated to the vehicle frame. These helpers give px4-selector and ap-consistency the
same view of an :class:`~imufdi_cli.array.ArrayConfig`: which IMUs carry a full triad of a
sensor type, their vectors in the body frame, and where each IMU axis sits in
``sensor_ids(type)`` (the index space of a DetectionBlock).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from imufdi_cli.array import ArrayConfig
from imufdi_cli.detectors.base import (
    NO_ISOLATION,
    NOT_ISOLABLE,
    DetectionBlock,
    DetectorBase,
    parse_sensor_types,
)
from imufdi_cli.errors import (
    ArrayTooSmallError,
    CalibrationError,
    DetectorConfigError,
    InputDataError,
)
from imufdi_cli.log import ImuBlock

#: Sensor types the firmware checks compare (magnetometers are checked differently).
VECTOR_TYPES: tuple[str, ...] = ("gyro", "accel")


def parse_vector_types(text: str, detector: str) -> tuple[str, ...]:
    """``"gyro,accel"`` -> ``("gyro", "accel")``; only gyro and accel are accepted."""
    types = parse_sensor_types(text, detector)
    for item in types:
        if item not in VECTOR_TYPES:
            raise DetectorConfigError(
                f"{detector}.types: {item!r} is not compared by this check; valid: gyro, accel"
            )
    return types


@dataclass
class TriadLayout:
    """The IMUs that carry a full triad of one sensor type.

    Attributes
    ----------
    sensor_type : str
    imus : ndarray, shape (m,), intp
        Array IMU index of each compared IMU (in array order).
    rotations : ndarray, shape (m, 3, 3)
        IMU frame -> body frame of each compared IMU.
    sensor_of : ndarray, shape (m, 3), intp
        Index in ``sensor_ids(sensor_type)`` of axis a of compared IMU k.
    sensor_ids : list of str
    """

    sensor_type: str
    imus: np.ndarray
    rotations: np.ndarray
    sensor_of: np.ndarray
    sensor_ids: list[str]

    @classmethod
    def build(cls, array: ArrayConfig, sensor_type: str, detector: str) -> TriadLayout:
        """Layout of ``sensor_type``; every IMU must have all three axes or none.

        Raises
        ------
        DetectorConfigError
            An IMU with one or two axes of the type (no vector to compare).
        """
        imu_index, axis_index = array.sensor_index(sensor_type)
        imus = np.unique(imu_index)
        sensor_of = np.full((imus.size, 3), -1, dtype=np.intp)
        for j, (k, a) in enumerate(zip(imu_index, axis_index)):
            sensor_of[np.searchsorted(imus, k), a] = j
        partial = [int(k) for k, row in zip(imus, sensor_of) if np.any(row < 0)]
        if partial:
            raise DetectorConfigError(
                f"{detector} compares whole {sensor_type} vectors; imu{partial[0]} has only"
                f" {int(np.sum(sensor_of[imus.tolist().index(partial[0])] >= 0))} of 3 axes"
            )
        rotations = array.rotations()[imus] if imus.size else np.zeros((0, 3, 3))
        return cls(sensor_type, imus, rotations, sensor_of, array.sensor_ids(sensor_type))

    @property
    def n_imus(self) -> int:
        return int(self.imus.size)

    @property
    def n_sensors(self) -> int:
        return len(self.sensor_ids)

    def body(self, block: ImuBlock, detector: str) -> np.ndarray:
        """Body-frame vectors of the compared IMUs, shape (N, m, 3), SI units.

        Raises
        ------
        InputDataError
            The block lacks the sensor type or has fewer IMUs than the layout.
        """
        triads = block.get(self.sensor_type)
        if triads is None:
            raise InputDataError(f"{detector}: block has no {self.sensor_type} data")
        if triads.shape[1] <= int(self.imus.max()):
            raise InputDataError(
                f"{detector}: block has {triads.shape[1]} IMUs but the array config has"
                f" {int(self.imus.max()) + 1}"
            )
        # v_body = R_k v_imu for every sample and IMU
        return np.einsum("kab,nkb->nka", self.rotations, triads[:, self.imus, :])

    def to_imu_frame(self, vectors: np.ndarray, imu: np.ndarray) -> np.ndarray:
        """Body-frame vectors (N, 3) of compared IMUs ``imu`` (N,) back to their IMU frames."""
        return np.einsum("nba,nb->na", self.rotations[imu], vectors)

    def calibration_offsets(self, calibration: ImuBlock, detector: str) -> np.ndarray:
        """Per-IMU mean offset from the array mean on a fault-free block, (m, 3), body frame.

        Stands in for the per-sensor offset calibration the firmware applies before its
        checks (gyro offsets at boot, stored accel offsets).
        """
        vectors = self.body(calibration, detector)
        if vectors.shape[0] < 10:
            raise CalibrationError(
                f"calibration window has {vectors.shape[0]} samples; {detector} needs at"
                " least 10 (use --calibrate START:END)"
            )
        if not np.all(np.isfinite(vectors)):
            raise CalibrationError(f"calibration window has non-finite {self.sensor_type} samples")
        deviation = vectors - vectors.mean(axis=1, keepdims=True)
        return np.asarray(deviation.mean(axis=0))

    def axis_rows(self, imu: np.ndarray, component: np.ndarray) -> np.ndarray:
        """Sensor index of (compared IMU, axis) pairs; NO_ISOLATION where imu < 0."""
        out = np.full(imu.shape, NO_ISOLATION, dtype=np.int32)
        valid = imu >= 0
        out[valid] = self.sensor_of[imu[valid], component[valid]]
        return out


def block_steps(t_ns: np.ndarray, last_ns: int | None, nominal_s: float) -> np.ndarray:
    """Time step of each sample, seconds (N,): from the previous timestamp, the first
    sample of a stream gets the nominal step ``nominal_s``."""
    t = np.asarray(t_ns, dtype=np.int64)
    previous = np.empty_like(t)
    if t.size:
        previous[0] = t[0] - round(nominal_s * 1e9) if last_ns is None else last_ns
        previous[1:] = t[:-1]
    return np.asarray((t - previous) * 1e-9, dtype=np.float64)


def compared_layouts(
    array: ArrayConfig, types: tuple[str, ...], detector: str
) -> dict[str, TriadLayout]:
    """The layout of every tested type that the array has, each with at least 2 IMUs.

    Raises
    ------
    DetectorConfigError
        A tested type with fewer than 2 IMUs (a type absent altogether is skipped when
        several are tested), a partial triad, or no tested type at all.
    """
    layouts = {}
    for sensor_type in types:
        layout = TriadLayout.build(array, sensor_type, detector)
        if layout.n_imus == 0 and len(types) > 1:
            continue
        if layout.n_imus < 2:
            raise ArrayTooSmallError(
                f"{detector} compares IMUs: {sensor_type} needs at least 2 IMUs,"
                f" the array has {layout.n_imus}"
            )
        layouts[sensor_type] = layout
    if not layouts:
        raise DetectorConfigError(f"{detector}: the array has no {' or '.join(types)} to compare")
    return layouts


def imu_isolation(
    layout: TriadLayout,
    alarm: np.ndarray,
    worst: np.ndarray,
    deviation: np.ndarray,
    imu_scores: np.ndarray,
    amplitude_scale: float = 1.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """DetectionBlock isolation columns from a whole-IMU decision.

    Parameters
    ----------
    alarm : ndarray, shape (N,), bool
    worst : ndarray, shape (N,), int
        The IMU (index into ``layout.imus``) blamed at each sample.
    deviation : ndarray, shape (N, m, 3)
        Each IMU's deviation from the others, body frame, SI.
    imu_scores : ndarray, shape (N, m)
        Per-IMU score, copied to each of the IMU's axes.
    amplitude_scale : float
        Factor from the deviation to the fault amplitude.

    Returns
    -------
    isolated : ndarray, shape (N,), int32
        The blamed IMU's axis with the largest deviation in its own frame (>= 3 IMUs), or
        NOT_ISOLABLE (2 IMUs), at alarmed samples; NO_ISOLATION elsewhere.
    amplitude : ndarray, shape (N,)
        That axis' deviation times ``amplitude_scale`` (NaN without isolation).
    scores : ndarray, shape (N, n_sensors)
    """
    n_samples, m = imu_scores.shape
    rows = np.arange(n_samples)
    local = layout.to_imu_frame(deviation[rows, worst], worst)  # (N, 3), IMU frame
    component = np.argmax(np.abs(local), axis=1)
    if m >= 3:
        isolated = np.where(alarm, layout.axis_rows(worst, component), NO_ISOLATION)
        amplitude = np.where(alarm, local[rows, component] * amplitude_scale, np.nan)
    else:
        isolated = np.where(alarm, NOT_ISOLABLE, NO_ISOLATION)
        amplitude = np.full(n_samples, np.nan)
    scores = np.full((n_samples, layout.n_sensors), np.nan)
    for axis in range(3):
        scores[:, layout.sensor_of[:, axis]] = imu_scores
    return isolated.astype(np.int32), amplitude, scores


__all__ = [
    "VECTOR_TYPES",
    "TriadLayout",
    "block_steps",
    "compared_layouts",
    "imu_isolation",
    "parse_vector_types",
]


class _TypeStateLike(Protocol):
    layout: TriadLayout


class CausalImuCheck(DetectorBase):
    """What px4-selector and ap-consistency share as detectors: one state per tested
    sensor type (``_states``, each with its :class:`TriadLayout`), filled by ``fit``, and
    one output row per input sample, so nothing is left to :meth:`flush`."""

    _states: Mapping[str, _TypeStateLike]

    def flush(self) -> dict[str, DetectionBlock]:
        """Causal: nothing is held back (an empty block per tested type)."""
        return {t: DetectionBlock.empty(0, s.layout.n_sensors) for t, s in self._states.items()}
