"""ArrayConfig: the geometry of a redundant IMU array, and its measurement matrices.

Each IMU k has a rotation ``R_k`` (IMU frame -> array body frame), a position ``r_k`` in
the body frame (metres) and, per sensor type, the axes that are present. For sensor type
``s`` the measurement of axis ``a`` of IMU ``k`` is the projection of the body-frame
quantity on that axis::

    m_{k,a} = (R_k^T w)_a = R_k[:, a] . w        (+ lever-arm terms for accelerometers)

so the measurement matrix ``H_s`` (n_s x 3) stacks the rows ``R_k[:, a]^T`` for every used
axis, IMU by IMU, axes in x, y, z order. Sensor ids are ``imu<k>.<type>.<axis>`` in the
same order (docs/formats.md, "ArrayConfig"). Co-aligned arrays, skewed single-axis arrays (e.g. six gyros on
a cone) and boards with rotated chips are all the same code.

The config is stored as TOML by users and as JSON in the ``imufdi.array`` metadata record
of every MCAP imufdi writes.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from imufdi_cli.errors import ArrayConfigError, UnitError
from imufdi_cli.tomlfile import parse_toml
from imufdi_cli.units import parse_quantity, sensor_dimension

SENSOR_TYPES: tuple[str, ...] = ("gyro", "accel", "mag")
AXES: tuple[str, ...] = ("x", "y", "z")


def quaternion_to_matrix(q: Sequence[float] | np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of a unit quaternion ``[w, x, y, z]`` (Hamilton, active)."""
    w, x, y, z = (float(v) for v in q)
    norm = math.sqrt(w * w + x * x + y * y + z * z)
    if norm == 0.0:
        raise ArrayConfigError("quaternion [0, 0, 0, 0] is not a rotation")
    w, x, y, z = w / norm, x / norm, y / norm, z / norm
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _check_rotation(matrix: np.ndarray, where: str) -> np.ndarray:
    matrix = np.asarray(matrix, dtype=float)
    if matrix.shape != (3, 3) or not np.all(np.isfinite(matrix)):
        raise ArrayConfigError(f"{where}: rotation must be a finite 3x3 matrix")
    with np.errstate(over="ignore", invalid="ignore"):  # 1e308 entries: not a rotation
        proper = np.allclose(matrix @ matrix.T, np.eye(3), atol=1e-6)
    if not proper or np.linalg.det(matrix) < 0:
        raise ArrayConfigError(
            f"{where}: rotation is not a proper rotation matrix (R R^T = I, det R = +1)"
        )
    return matrix


def _parse_axes(value: Any, where: str) -> tuple[str, ...]:
    if isinstance(value, str):
        items = list(value.replace(",", "").replace(" ", ""))
    elif isinstance(value, (list, tuple)):
        items = [str(v) for v in value]
    else:
        raise ArrayConfigError(f"{where}: axes must be a string like 'xyz' or a list")
    for item in items:
        if item not in AXES:
            raise ArrayConfigError(f"{where}: unknown axis {item!r}; valid: x, y, z")
    if len(set(items)) != len(items):
        raise ArrayConfigError(f"{where}: repeated axis in {value!r}")
    return tuple(a for a in AXES if a in items)


@dataclass(frozen=True, eq=False)
class TriadCalibration:
    """Per-chip calibration of one sensor triad: ``calibrated = M (raw - b)``.

    ``M`` absorbs scale factors (diagonal), non-orthogonality and a small residual
    rotation of the chip; ``b`` is the bias in the raw (chip) frame, SI units.

    Attributes
    ----------
    matrix : ndarray, shape (3, 3)
        ``M``, dimensionless; must be finite and well conditioned.
    bias : ndarray, shape (3,)
        ``b``, rad/s (gyro), m/s^2 (accel) or tesla (mag).
    """

    matrix: np.ndarray = field(default_factory=lambda: np.eye(3))
    bias: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def apply(self, raw: np.ndarray) -> np.ndarray:
        """``M (raw - b)`` for triads ``raw`` (..., 3)."""
        with np.errstate(over="ignore", invalid="ignore"):
            return (np.asarray(raw, float) - self.bias) @ self.matrix.T

    def undo(self, calibrated: np.ndarray) -> np.ndarray:
        """The raw triads (..., 3) that :meth:`apply` maps to ``calibrated``."""
        with np.errstate(over="ignore", invalid="ignore"):
            return np.asarray(calibrated, float) @ np.linalg.inv(self.matrix).T + self.bias

    @property
    def is_identity(self) -> bool:
        return bool(np.array_equal(self.matrix, np.eye(3)) and not np.any(self.bias))


#: Largest condition number accepted for a calibration matrix M (a chip whose M is worse
#: is a typo or a failed fit, not a sensor).
MAX_CALIBRATION_CONDITION = 1e3


def _check_calibration(matrix: Any, bias: Any, where: str, unit: str) -> TriadCalibration:
    try:
        m = np.asarray(matrix, dtype=float)
        b = np.asarray(
            [parse_quantity(v, unit, name=where) if isinstance(v, str) else v for v in bias]
            if isinstance(bias, (list, tuple))
            else bias,
            dtype=float,
        )
    except (TypeError, ValueError, OverflowError, UnitError) as err:
        raise ArrayConfigError(f"{where}: calibration must be numbers ({err})") from err
    if m.shape != (3, 3):
        raise ArrayConfigError(f"{where}: matrix must be 3x3, got shape {m.shape}")
    if b.shape != (3,):
        raise ArrayConfigError(f"{where}: bias must be [x, y, z], got shape {b.shape}")
    if not (np.all(np.isfinite(m)) and np.all(np.isfinite(b))):
        raise ArrayConfigError(f"{where}: matrix and bias must be finite")
    cond = np.linalg.cond(m)
    if not np.isfinite(cond) or cond > MAX_CALIBRATION_CONDITION:
        raise ArrayConfigError(
            f"{where}: matrix is singular or nearly so (condition number {cond:.3g},"
            f" limit {MAX_CALIBRATION_CONDITION:g})"
        )
    return TriadCalibration(matrix=m, bias=b)


def _check_noise(value: Any, where: str, sensor_type: str) -> np.ndarray:
    """A per-axis noise sigma ``[x, y, z]`` (numbers in SI or quantities with units)."""
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        raise ArrayConfigError(f"{where}: must be [x, y, z] noise sigmas")
    try:
        out = np.asarray(
            [
                parse_quantity(v, sensor_dimension(sensor_type), name=where)
                if isinstance(v, str)
                else float(v)
                for v in value
            ],
            dtype=float,
        )
    except (TypeError, ValueError, OverflowError, UnitError) as err:
        raise ArrayConfigError(f"{where}: noise must be numbers ({err})") from err
    if not (np.all(np.isfinite(out)) and np.all(out > 0)):
        raise ArrayConfigError(f"{where}: noise sigmas must be positive and finite")
    return out


def _check_spread(value: Any, where: str) -> np.ndarray:
    """A per-axis noise-variance spread ``[x, y, z]``, each >= 1 and finite."""
    try:
        out = np.asarray(value, dtype=float)
    except (TypeError, ValueError, OverflowError) as err:
        raise ArrayConfigError(f"{where}: must be [x, y, z] numbers ({err})") from err
    if out.shape != (3,):
        raise ArrayConfigError(f"{where}: must be [x, y, z] variance factors")
    if not (np.all(np.isfinite(out)) and np.all(out >= 1.0)):
        raise ArrayConfigError(f"{where}: variance factors must be finite and >= 1")
    return out.copy()


@dataclass(frozen=True, eq=False)
class ImuSpec:
    """One IMU of the array.

    Attributes
    ----------
    rotation : ndarray, shape (3, 3)
        IMU frame -> array body frame.
    position : ndarray, shape (3,)
        Position of the IMU in the body frame, metres.
    axes : dict
        Per sensor type (``gyro``, ``accel``, ``mag``) the axes present, e.g. ``("x","y","z")``;
        an empty tuple means the IMU has no such sensor.
    calibration : dict
        Per sensor type, the chip's :class:`TriadCalibration` (absent: identity).
    noise : dict
        Per sensor type, the white-noise standard deviation of each axis after
        calibration, shape (3,), SI (``imufdi calibrate`` measures it over every static
        orientation of a log). Absent: the array-wide ``ArrayConfig.noise``.
    noise_spread : dict
        Per sensor type, each axis' healthy noise-variance spread kappa >= 1, shape (3,),
        dimensionless: over the static orientations of a calibration log the axis' white-
        noise variance (from successive differences) ranged over a factor kappa, max over
        min, net of the sampling error (``imufdi calibrate``,
        :func:`imufdi_cli.calibrate.noise_spread`). noise-glr then tests growth beyond
        kappa times the variance of its calibration window. Absent: no spread (1).
    """

    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    position: np.ndarray = field(default_factory=lambda: np.zeros(3))
    axes: Mapping[str, tuple[str, ...]] = field(
        default_factory=lambda: {"gyro": AXES, "accel": AXES, "mag": ()}
    )
    calibration: Mapping[str, TriadCalibration] = field(default_factory=dict)
    noise: Mapping[str, np.ndarray] = field(default_factory=dict)
    noise_spread: Mapping[str, np.ndarray] = field(default_factory=dict)

    def axes_of(self, sensor_type: str) -> tuple[str, ...]:
        return tuple(self.axes.get(sensor_type, ()))

    def calibration_of(self, sensor_type: str) -> TriadCalibration:
        """The chip calibration of a sensor type (identity when none is given)."""
        return self.calibration.get(sensor_type) or TriadCalibration()


@dataclass(frozen=True, eq=False)
class ArrayConfig:
    """Geometry, sample rate and nominal noise of an IMU array.

    Attributes
    ----------
    imus : tuple of ImuSpec
        IMU k publishes on ``/imu<k>/data_raw`` and has sensor ids ``imu<k>.<type>.<axis>``.
    rate_hz : float
        Nominal sample rate, Hz.
    noise : dict
        Nominal white-noise standard deviation per sensor type in SI units (rad/s, m/s^2,
        tesla). Optional; detectors calibrate from data when it is absent.
    range : dict
        Measurement range (full scale) per sensor type, SI; samples at or near it are
        flagged as clipped (:mod:`imufdi_cli.validity`). Optional.
    jitter : dict
        Sampling-time jitter sigma_t per sensor type, seconds (``imufdi calibrate`` fits
        it from the motion of a log; :mod:`imufdi_cli.maths.jitter`): in motion each
        sensor's noise variance grows by about ``sigma_t^2 |dm/dt|^2``, and glt and
        pca-parity widen their tests by that much. Optional; absent or 0: no motion term.
    """

    imus: tuple[ImuSpec, ...]
    rate_hz: float = 100.0
    noise: Mapping[str, float] = field(default_factory=dict)
    range: Mapping[str, float] = field(default_factory=dict)
    jitter: Mapping[str, float] = field(default_factory=dict)
    # sensor_index per sensor type, computed at first use (the IMUs are immutable)
    _sensor_index: dict[str, tuple[np.ndarray, np.ndarray]] = field(
        default_factory=dict, init=False, repr=False, compare=False
    )

    def __post_init__(self) -> None:
        if len(self.imus) == 0:
            raise ArrayConfigError("an array needs at least one IMU")
        if not (math.isfinite(self.rate_hz) and self.rate_hz > 0):
            raise ArrayConfigError(f"rate_hz must be a positive number, got {self.rate_hz!r}")

    def __eq__(self, other: object) -> bool:
        return isinstance(other, ArrayConfig) and self.to_dict() == other.to_dict()

    def __hash__(self) -> int:
        return hash(self.to_json())

    # --- construction helpers -------------------------------------------------------

    @classmethod
    def co_aligned(
        cls,
        n_imus: int,
        rate_hz: float = 100.0,
        *,
        sensors: Sequence[str] = ("gyro", "accel"),
        positions: np.ndarray | None = None,
        noise: Mapping[str, float] | None = None,
    ) -> ArrayConfig:
        """``n_imus`` IMUs with identity rotation; positions (n_imus, 3) in metres."""
        if n_imus < 1:
            raise ArrayConfigError(f"number of IMUs must be >= 1, got {n_imus}")
        pos = np.zeros((n_imus, 3)) if positions is None else np.asarray(positions, float)
        imus = tuple(
            ImuSpec(
                rotation=np.eye(3),
                position=pos[k].copy(),
                axes={s: (AXES if s in sensors else ()) for s in SENSOR_TYPES},
            )
            for k in range(n_imus)
        )
        return cls(imus=imus, rate_hz=rate_hz, noise=dict(noise or {}))

    # --- sensors --------------------------------------------------------------------

    @property
    def n_imus(self) -> int:
        return len(self.imus)

    def has(self, sensor_type: str) -> bool:
        """Whether any IMU has at least one axis of this sensor type."""
        return any(imu.axes_of(sensor_type) for imu in self.imus)

    def sensor_types(self) -> list[str]:
        """Sensor types present in the array, in gyro, accel, mag order."""
        return [s for s in SENSOR_TYPES if self.has(s)]

    def sensor_index(self, sensor_type: str) -> tuple[np.ndarray, np.ndarray]:
        """IMU index and axis index (0..2) of each used sensor of a type, shapes (n,), (n,).

        Built once per array and sensor type and returned read-only (every block's
        :meth:`select` asks for it; building it is a Python loop over the IMUs' axes).
        """
        cached = self._sensor_index.get(sensor_type)
        if cached is not None:
            return cached
        _check_type(sensor_type)
        imu_idx: list[int] = []
        axis_idx: list[int] = []
        for k, imu in enumerate(self.imus):
            for a in imu.axes_of(sensor_type):
                imu_idx.append(k)
                axis_idx.append(AXES.index(a))
        index = np.asarray(imu_idx, dtype=np.intp), np.asarray(axis_idx, dtype=np.intp)
        for part in index:
            part.flags.writeable = False
        self._sensor_index[sensor_type] = index
        return index

    def sensor_ids(self, sensor_type: str) -> list[str]:
        """``imu<k>.<type>.<axis>`` for every used sensor of a type, in H row order."""
        imu_idx, axis_idx = self.sensor_index(sensor_type)
        return [f"imu{k}.{sensor_type}.{AXES[a]}" for k, a in zip(imu_idx, axis_idx)]

    def n_sensors(self, sensor_type: str) -> int:
        return int(self.sensor_index(sensor_type)[0].size)

    def measurement_matrix(self, sensor_type: str) -> np.ndarray:
        """H_s, shape (n_s, 3): row j is the body-frame direction of sensor j's axis."""
        imu_idx, axis_idx = self.sensor_index(sensor_type)
        if imu_idx.size == 0:
            return np.zeros((0, 3))
        rotations = np.stack([imu.rotation for imu in self.imus])  # (m, 3, 3)
        return rotations[imu_idx, :, axis_idx]  # row j = R_k[:, a]

    def sensor_noise(self, sensor_type: str) -> np.ndarray | None:
        """Per-sensor noise sigma (n_s,), SI, in sensor-id order: each IMU's ``<type>_noise``
        where given, else the array-wide ``noise.<type>``; None when some sensor has
        neither."""
        return self._per_sensor(sensor_type, lambda imu: imu.noise, self.noise.get(sensor_type))

    def sensor_noise_spread(self, sensor_type: str) -> np.ndarray | None:
        """Per-sensor healthy noise-variance spread kappa (n_s,) in sensor-id order (each
        IMU's ``<type>_noise_spread``); None unless every IMU with that type carries one."""
        return self._per_sensor(sensor_type, lambda imu: imu.noise_spread)

    def _per_sensor(
        self,
        sensor_type: str,
        table: Callable[[ImuSpec], Mapping[str, np.ndarray]],
        common: float | None = None,
    ) -> np.ndarray | None:
        """Per-sensor values (n_s,) in sensor-id order from each IMU's per-axis ``table``
        entry for ``sensor_type``, else ``common``; None when some sensor has neither."""
        imu_idx, axis_idx = self.sensor_index(sensor_type)
        out = np.empty(imu_idx.size)
        for j, (k, a) in enumerate(zip(imu_idx, axis_idx)):
            per = table(self.imus[k]).get(sensor_type)
            if per is not None:
                out[j] = float(per[a])
            elif common is not None:
                out[j] = float(common)
            else:
                return None
        return out

    def with_noise_spread(self, spread: Sequence[Mapping[str, np.ndarray]]) -> ArrayConfig:
        """This array with each IMU's per-axis noise-variance spreads replaced (one dict per
        IMU; values >= 1)."""
        if len(spread) != self.n_imus:
            raise ArrayConfigError(f"{len(spread)} spread tables given for {self.n_imus} IMUs")
        imus = tuple(
            replace(
                imu,
                noise_spread={
                    s: _check_spread(v, f"imu{k} {s}_noise_spread") for s, v in n.items()
                },
            )
            for k, (imu, n) in enumerate(zip(self.imus, spread))
        )
        return replace(self, imus=imus)

    @property
    def per_sensor_noise(self) -> bool:
        """Whether any IMU carries its own per-axis noise levels."""
        return any(imu.noise for imu in self.imus)

    def with_sensor_noise(self, noise: Sequence[Mapping[str, np.ndarray]]) -> ArrayConfig:
        """This array with each IMU's per-axis noise sigmas replaced (one dict per IMU)."""
        if len(noise) != self.n_imus:
            raise ArrayConfigError(f"{len(noise)} noise tables given for {self.n_imus} IMUs")
        imus = tuple(
            replace(imu, noise={s: np.asarray(v, float).copy() for s, v in n.items()})
            for imu, n in zip(self.imus, noise)
        )
        return replace(self, imus=imus)

    def positions(self) -> np.ndarray:
        """IMU positions in the body frame, shape (m, 3), metres."""
        return np.stack([np.asarray(imu.position, float) for imu in self.imus])

    def rotations(self) -> np.ndarray:
        """IMU -> body rotations, shape (m, 3, 3)."""
        return np.stack([np.asarray(imu.rotation, float) for imu in self.imus])

    def select(self, triads: np.ndarray, sensor_type: str) -> np.ndarray:
        """Flatten per-IMU triads (N, m, 3) to the used sensors (N, n_s), in sensor-id order."""
        imu_idx, axis_idx = self.sensor_index(sensor_type)
        return np.asarray(triads)[:, imu_idx, axis_idx]

    def calibrate_triads(
        self, triads: np.ndarray, sensor_type: str, *, undo: bool = False
    ) -> np.ndarray:
        """Each IMU's chip calibration applied to its triads, ``M (raw - b)`` (or undone:
        ``undo=True`` gives the raw values back).

        Parameters
        ----------
        triads : ndarray, shape (N, m, 3), SI
        sensor_type : str

        Returns
        -------
        ndarray, shape (N, m, 3): a new array (the input is not modified).
        """
        out = np.array(triads, dtype=np.float64, copy=True)
        for k, imu in enumerate(self.imus):
            cal = imu.calibration_of(sensor_type)
            if not cal.is_identity:
                out[:, k] = cal.undo(out[:, k]) if undo else cal.apply(out[:, k])
        return out

    # --- serialisation --------------------------------------------------------------

    def to_dict(self) -> dict[str, Any]:
        """A JSON/TOML-ready dict (SI units)."""
        data: dict[str, Any] = {
            "rate_hz": float(self.rate_hz),
            "noise": {k: float(v) for k, v in self.noise.items()},
            "imu": [
                {
                    "rotation": np.asarray(imu.rotation, float).tolist(),
                    "position": np.asarray(imu.position, float).tolist(),
                    **{f"{s}_axes": "".join(imu.axes_of(s)) for s in SENSOR_TYPES},
                    **{
                        key: value
                        for s, cal in imu.calibration.items()
                        for key, value in (
                            (f"{s}_matrix", np.asarray(cal.matrix, float).tolist()),
                            (f"{s}_bias", np.asarray(cal.bias, float).tolist()),
                        )
                    },
                    **{f"{s}_noise": np.asarray(v, float).tolist() for s, v in imu.noise.items()},
                    **{
                        f"{s}_noise_spread": np.asarray(v, float).tolist()
                        for s, v in imu.noise_spread.items()
                    },
                }
                for imu in self.imus
            ],
        }
        if self.range:
            data["range"] = {k: float(v) for k, v in self.range.items()}
        if self.jitter:
            data["jitter"] = {k: float(v) for k, v in self.jitter.items()}
        return data

    @property
    def calibrated(self) -> bool:
        """Whether any IMU carries a non-identity chip calibration."""
        return any(not c.is_identity for imu in self.imus for c in imu.calibration.values())

    def with_calibration(
        self, calibration: Sequence[Mapping[str, TriadCalibration]] | None
    ) -> ArrayConfig:
        """This geometry with the per-IMU calibrations replaced (None: removed)."""
        cals = calibration or [{} for _ in self.imus]
        if len(cals) != self.n_imus:
            raise ArrayConfigError(
                f"{len(cals)} calibrations given for an array of {self.n_imus} IMUs"
            )
        imus = tuple(replace(imu, calibration=dict(c)) for imu, c in zip(self.imus, cals))
        return replace(self, imus=imus)

    def check_matches(self, log_array: ArrayConfig) -> ArrayConfig:
        """This config (``--array FILE``) checked against a log's: same IMU count and
        every sensor type of the log present. Returns self."""
        if self.n_imus != log_array.n_imus:
            raise ArrayConfigError(
                f"--array describes {self.n_imus} IMUs but the log has {log_array.n_imus}"
            )
        for s in log_array.sensor_types():
            if not self.has(s):
                raise ArrayConfigError(f"--array has no {s} axes but the log has {s} data")
        return self

    def with_range(self, ranges: Mapping[str, float]) -> ArrayConfig:
        """This array with the measurement ranges of ``ranges`` added where none is set."""
        merged = {**{k: float(v) for k, v in ranges.items()}, **dict(self.range)}
        return replace(self, range=merged)

    def with_jitter(self, jitter: Mapping[str, float]) -> ArrayConfig:
        """This array with its sampling-time jitter table replaced (seconds per type)."""
        checked = {k: _check_jitter(v, f"jitter.{k}") for k, v in jitter.items()}
        for key in checked:
            _check_type(key)
        return replace(self, jitter=checked)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], *, source: str = "array config") -> ArrayConfig:
        """Build from the dict form (TOML or JSON); quantities may carry units."""
        if not isinstance(data, Mapping):
            raise ArrayConfigError(f"{source}: expected a table at the top level")
        known = {"rate_hz", "rate", "noise", "imu", "range", "jitter"}
        for key in data:
            if key not in known:
                raise ArrayConfigError(
                    f"{source}: unknown key {key!r}; valid: {', '.join(sorted(known))}"
                )
        try:
            if "rate" in data:
                rate = parse_quantity(data["rate"], "frequency", name=f"{source}: rate")
            else:
                rate = _number(data.get("rate_hz", 100.0), f"{source}: rate_hz", "100")
            noise = _per_type_quantities(data, "noise", "{gyro = '0.1deg/s'}", source)
            ranges = _per_type_quantities(
                data, "range", "{gyro = '2000deg/s', accel = '16g'}", source
            )
            for key in ranges:
                if not (math.isfinite(ranges[key]) and ranges[key] > 0):
                    raise ArrayConfigError(f"{source}: range.{key} must be positive and finite")
            jitter = _per_type_quantities(data, "jitter", "{gyro = '0.3ms'}", source, "time")
            for key in jitter:
                _check_jitter(jitter[key], f"{source}: jitter.{key}")
        except UnitError as err:
            raise ArrayConfigError(str(err)) from err
        imus_raw = data.get("imu")
        if not isinstance(imus_raw, list) or not imus_raw:
            raise ArrayConfigError(f"{source}: needs at least one [[imu]] table")
        imus = []
        imu_keys = {
            "rotation",
            "quaternion",
            "position",
            *(
                f"{s}_{key}"
                for s in SENSOR_TYPES
                for key in ("axes", "matrix", "bias", "noise", "noise_spread")
            ),
        }
        for k, item in enumerate(imus_raw):
            where = f"{source}: imu[{k}]"
            if not isinstance(item, Mapping):
                raise ArrayConfigError(f"{where}: expected a table")
            for key in item:
                if key not in imu_keys:
                    raise ArrayConfigError(
                        f"{where}: unknown key {key!r}; valid: {', '.join(sorted(imu_keys))}"
                    )
            if "rotation" in item and "quaternion" in item:
                raise ArrayConfigError(f"{where}: give rotation or quaternion, not both")
            try:
                if "quaternion" in item:
                    quat = np.asarray(item["quaternion"], dtype=float)
                    if quat.shape != (4,):
                        raise ArrayConfigError(f"{where}: quaternion must be [w, x, y, z]")
                    rotation = quaternion_to_matrix(quat)
                else:
                    rotation = np.asarray(item.get("rotation", np.eye(3)), dtype=float)
                position = np.asarray(item.get("position", [0.0, 0.0, 0.0]), dtype=float)
            except (TypeError, ValueError, OverflowError) as err:
                raise ArrayConfigError(f"{where}: rotation/position must be numbers") from err
            if position.shape != (3,) or not np.all(np.isfinite(position)):
                raise ArrayConfigError(f"{where}: position must be [x, y, z] in metres")
            axes = {
                s: _parse_axes(item.get(f"{s}_axes", "xyz" if s != "mag" else ""), where)
                for s in SENSOR_TYPES
            }
            calibration = {}
            for s in SENSOR_TYPES:
                if f"{s}_matrix" in item or f"{s}_bias" in item:
                    calibration[s] = _check_calibration(
                        item.get(f"{s}_matrix", np.eye(3).tolist()),
                        item.get(f"{s}_bias", [0.0, 0.0, 0.0]),
                        f"{source}: imu{k} {s} calibration",
                        sensor_dimension(s),
                    )
            sensor_noise = {
                s: _check_noise(item[f"{s}_noise"], f"{source}: imu{k} {s}_noise", s)
                for s in SENSOR_TYPES
                if f"{s}_noise" in item
            }
            spread = {
                s: _check_spread(item[f"{s}_noise_spread"], f"{source}: imu{k} {s}_noise_spread")
                for s in SENSOR_TYPES
                if f"{s}_noise_spread" in item
            }
            imus.append(
                ImuSpec(
                    rotation=_check_rotation(rotation, where),
                    position=position,
                    axes=axes,
                    calibration=calibration,
                    noise=sensor_noise,
                    noise_spread=spread,
                )
            )
        return cls(imus=tuple(imus), rate_hz=rate, noise=noise, range=ranges, jitter=jitter)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), separators=(",", ":"))

    @classmethod
    def from_json(cls, text: str | bytes, *, source: str = "imufdi.array metadata") -> ArrayConfig:
        from imufdi_cli.jsonin import loads

        return cls.from_dict(loads(text, source, ArrayConfigError), source=source)

    def to_toml(self) -> str:
        """The TOML form users edit (SI numbers)."""
        lines = [f"rate_hz = {self.rate_hz!r}", ""]
        if self.noise:
            lines.append("[noise]  # white-noise sigma, SI (rad/s, m/s^2, T)")
            lines += [f"{k} = {float(v)!r}" for k, v in self.noise.items()]
            lines.append("")
        if self.range:
            lines.append("[range]  # full scale, SI (rad/s, m/s^2, T): samples near it are clipped")
            lines += [f"{k} = {float(v)!r}" for k, v in self.range.items()]
            lines.append("")
        if self.jitter:
            lines.append(
                "[jitter]  # sampling-time jitter sigma_t, s: in motion the noise variance grows"
                " by sigma_t^2 |dm/dt|^2"
            )
            lines += [f"{k} = {float(v)!r}" for k, v in self.jitter.items()]
            lines.append("")
        for k, imu in enumerate(self.imus):
            rot = ", ".join(
                "[" + ", ".join(repr(float(v)) for v in row) + "]"
                for row in np.asarray(imu.rotation)
            )
            pos = ", ".join(repr(float(v)) for v in np.asarray(imu.position))
            lines += [
                "[[imu]]",
                f"rotation = [{rot}]  # IMU frame -> body frame",
                f"position = [{pos}]  # m, body frame",
            ]
            lines += [f'{s}_axes = "{"".join(imu.axes_of(s))}"' for s in SENSOR_TYPES]
            for s, cal in imu.calibration.items():
                mat = ", ".join(
                    "[" + ", ".join(repr(float(v)) for v in row) + "]"
                    for row in np.asarray(cal.matrix)
                )
                bias = ", ".join(repr(float(v)) for v in np.asarray(cal.bias))
                lines += [
                    f"{s}_matrix = [{mat}]  # imu{k}: calibrated = M (raw - b)",
                    f"{s}_bias = [{bias}]  # SI, chip frame",
                ]
            for s, sig in imu.noise.items():
                values = ", ".join(repr(float(v)) for v in np.asarray(sig))
                lines.append(f"{s}_noise = [{values}]  # white-noise sigma per axis, SI")
            for s, kappa in imu.noise_spread.items():
                values = ", ".join(repr(float(v)) for v in np.asarray(kappa))
                lines.append(
                    f"{s}_noise_spread = [{values}]  # healthy noise-variance spread over"
                    " orientations (max/min, >= 1)"
                )
            lines.append("")
        return "\n".join(lines)

    @classmethod
    def load(cls, path: str | Path) -> ArrayConfig:
        """Load a TOML (or JSON, by extension) array config file."""
        path = Path(path)
        try:
            raw = path.read_bytes()
        except OSError as err:
            raise ArrayConfigError(f"cannot read array config {path}: {err.strerror}") from err
        if path.suffix.lower() == ".json":
            return cls.from_json(raw, source=str(path))
        return cls.from_dict(parse_toml(raw, path, ArrayConfigError), source=str(path))

    def save(self, path: str | Path) -> None:
        from imufdi_cli.fileio import write_text

        write_text(str(path), self.to_toml())

    def with_imus(self, n_imus: int) -> ArrayConfig:
        """The first ``n_imus`` IMUs of this array (used when a log has fewer topics)."""
        return ArrayConfig(
            imus=self.imus[:n_imus],
            rate_hz=self.rate_hz,
            noise=dict(self.noise),
            range=dict(self.range),
            jitter=dict(self.jitter),
        )


def _number(value: Any, where: str, example: str) -> float:
    """A plain number from a TOML/JSON value (ArrayConfigError naming it otherwise)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ArrayConfigError(
            f"{where} must be a number (e.g. {example}), got {value!r}"
            if not isinstance(value, (list, dict))
            else f"{where} must be a number (e.g. {example}), got a {type(value).__name__}"
        )
    try:
        return float(value)
    except OverflowError as err:
        raise ArrayConfigError(f"{where} is too large") from err


def _check_jitter(value: Any, where: str) -> float:
    """A sampling-time jitter sigma in seconds: finite and >= 0."""
    try:
        out = float(value)
    except (TypeError, ValueError, OverflowError) as err:
        raise ArrayConfigError(f"{where}: must be a time in seconds") from err
    if not (math.isfinite(out) and out >= 0):
        raise ArrayConfigError(f"{where}: must be finite and >= 0 seconds, got {value!r}")
    return out


def _per_type_quantities(
    data: Mapping[str, Any], key: str, example: str, source: str, dimension: str | None = None
) -> dict[str, float]:
    """A ``[key]`` table of one quantity per sensor type (``noise``, ``range``, ``jitter``),
    in SI; ``dimension`` overrides the sensor type's own (e.g. ``time`` for jitter)."""
    raw = data.get(key, {})
    if not isinstance(raw, Mapping):
        raise ArrayConfigError(f"{source}: {key} must be a table like {example}")
    out: dict[str, float] = {}
    for sensor_type, value in raw.items():
        if sensor_type not in SENSOR_TYPES:
            raise ArrayConfigError(
                f"{source}: {key}.{sensor_type}: unknown sensor type; valid: gyro, accel, mag"
            )
        out[sensor_type] = parse_quantity(
            value, dimension or sensor_dimension(sensor_type), name=f"{source}: {key}.{sensor_type}"
        )
    return out


def _check_type(sensor_type: str) -> None:
    if sensor_type not in SENSOR_TYPES:
        raise ArrayConfigError(
            f"unknown sensor type {sensor_type!r}; valid: {', '.join(SENSOR_TYPES)}"
        )


def parse_sensor_id(text: str, array: ArrayConfig) -> tuple[int, str, tuple[str, ...]]:
    """Parse ``imu3.gyro.z`` (one axis) or ``imu3.gyro`` (the triad's used axes).

    Returns ``(imu_index, sensor_type, axes)``. Raises ArrayConfigError naming valid choices.
    """
    parts = text.strip().split(".")
    if len(parts) not in (2, 3) or not parts[0].startswith("imu") or not parts[0][3:].isdigit():
        raise ArrayConfigError(
            f"sensor {text!r} is not of the form imu<k>.<gyro|accel|mag>[.<x|y|z>]"
        )
    k = int(parts[0][3:])
    if k >= array.n_imus:
        raise ArrayConfigError(
            f"sensor {text!r}: IMU index {k} is past the array (imu0..imu{array.n_imus - 1})"
        )
    sensor_type = parts[1]
    _check_type(sensor_type)
    present = array.imus[k].axes_of(sensor_type)
    if not present:
        raise ArrayConfigError(f"sensor {text!r}: imu{k} has no {sensor_type}")
    if len(parts) == 3:
        if parts[2] not in present:
            raise ArrayConfigError(
                f"sensor {text!r}: axis {parts[2]!r} is not present; valid: {', '.join(present)}"
            )
        return k, sensor_type, (parts[2],)
    return k, sensor_type, present
