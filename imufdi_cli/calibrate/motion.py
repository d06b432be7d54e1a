"""What calibrate learns from the motion: chip time offsets (a diagnostic) and the
sampling-time jitter term ``[jitter]`` of :mod:`imufdi_cli.maths.jitter`."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from imufdi_cli.array import ArrayConfig
from imufdi_cli.calibrate.static import STATIC_WINDOW_S
from imufdi_cli.errors import ArrayConfigError
from imufdi_cli.maths.jitter import fit_jitter
from imufdi_cli.maths.rigid import accel_design
from imufdi_cli.validity import flag_values

#: Warn when a chip time offset explains more than this share of its motion residual.
TIME_OFFSET_WARNING = 0.1


def time_offsets(
    array: ArrayConfig, gyro: np.ndarray, t_s: np.ndarray, motion: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per-IMU sampling-time offset from calibrated gyro triads in motion.

    Each chip's body-frame rate minus the array consensus ``w`` is regressed on the
    consensus angular acceleration ``w_dot`` (central differences):
    ``R_k w_k - w ~ w_dot dt_k``, least squares over the motion rows and three axes
    (:class:`TimeOffsetSums`, which ``calibrate`` streams).

    Parameters
    ----------
    array : ArrayConfig
    gyro : ndarray, shape (N, m, 3)
        Calibrated rates, rad/s (IMU frames).
    t_s : ndarray, shape (N,)
    motion : ndarray, shape (N,), bool
        Rows to use (moving, not clipped; their neighbours enter the differences).

    Returns
    -------
    offsets : ndarray, shape (m,), s
        Relative to the array's mean sampling instant (they sum to ~0).
    explained : ndarray, shape (m,)
        Share of each chip's residual energy on those rows that the offset explains.
    """
    m = gyro.shape[1]
    if np.count_nonzero(motion) < 3 or len(t_s) < 3:
        return np.zeros(m), np.zeros(m)
    body = np.einsum("kij,nkj->nki", array.rotations(), gyro)
    consensus = body.mean(axis=1)
    rate_dot = np.gradient(consensus, t_s, axis=0)  # (N, 3)
    sums = TimeOffsetSums(m)
    sums.add(body[motion], consensus[motion], rate_dot[motion])
    return sums.result()


class TimeOffsetSums:
    """The sums :func:`time_offsets` regresses with, over rows added in blocks: ``sum x^2``
    of the consensus angular acceleration, and per chip ``sum x y_k`` and ``sum y_k^2`` of
    its body-frame rate minus the consensus."""

    def __init__(self, m: int) -> None:
        self.xx = 0.0
        self.xy = np.zeros(m)
        self.yy = np.zeros(m)
        self.rows = 0

    def add(self, body: np.ndarray, consensus: np.ndarray, rate_dot: np.ndarray) -> None:
        """Rows: body-frame rates (k, m, 3), their consensus (k, 3) and its derivative (k, 3)."""
        if body.shape[0] == 0:
            return
        y = body - consensus[:, None, :]
        self.xx += float(np.sum(rate_dot * rate_dot))
        self.xy += np.einsum("nka,na->k", y, rate_dot)
        self.yy += np.sum(y * y, axis=(0, 2))
        self.rows += int(body.shape[0])

    def result(self) -> tuple[np.ndarray, np.ndarray]:
        m = self.xy.shape[0]
        offsets, explained = np.zeros(m), np.zeros(m)
        if self.xx <= 0:
            return offsets, explained
        offsets = self.xy / self.xx
        left = self.yy - 2.0 * offsets * self.xy + offsets**2 * self.xx  # sum (y - dt x)^2
        positive = self.yy > 0
        explained[positive] = 1.0 - left[positive] / self.yy[positive]
        return offsets, explained


def _zero_clipped_rows(
    array: ArrayConfig, accel: np.ndarray, gyro: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Rows with any clipped or invalid accel/gyro value (per the array's ranges), zeroed.

    Returns ``(accel (N, m, 3), gyro (N, m, 3) or None, clipped (N,) bool)``.
    """
    clipped = np.zeros(accel.shape[0], dtype=bool)
    for s, data in (("accel", accel), ("gyro", gyro)):
        if data is not None:
            c, i = flag_values(data, s, array.range.get(s))
            clipped |= (c | i).any(axis=(1, 2))
    accel = np.where(clipped[:, None, None], 0.0, accel)
    gyro = None if gyro is None else np.where(clipped[:, None, None], 0.0, gyro)
    return accel, gyro, clipped


def motion_rows(array: ArrayConfig, static: np.ndarray, clipped: np.ndarray) -> np.ndarray:
    """Rows (N,) bool more than one static window away from any static row, not clipped."""
    w = round(STATIC_WINDOW_S * array.rate_hz)
    near_static = np.convolve(static.astype(float), np.ones(2 * w + 1), "same") > 0
    return np.asarray(~near_static & ~clipped)


#: ``calibrate --jitter-fit`` choices: the per-sample level the fit holds in motion.
JITTER_FITS = ("level", "moments", "off")
JITTER_LEVEL_ALPHA = 0.01


def jitter_stage(
    array: ArrayConfig,
    fields: dict[str, np.ndarray | None],
    t_s: np.ndarray,
    static: np.ndarray,
    clipped: np.ndarray,
    method: str = "level",
    *,
    values: Mapping[str, np.ndarray] | None = None,
) -> dict[str, float]:
    """Sampling-time jitter sigma_t (s) per sensor type with a parity space and per-sensor
    noise, fitted on the motion rows (:func:`imufdi_cli.maths.jitter.fit_jitter`):
    ``method`` ``level`` (the per-sample test at alpha = 1 % holds its level on those rows),
    ``moments`` or ``off`` (nothing fitted).

    Parameters
    ----------
    array : ArrayConfig
        With the chip calibration and noise levels to use.
    fields : dict
        Raw triads (N, m, 3) per sensor type (None: absent), clipped rows zeroed.
    t_s : (N,) s; static, clipped : (N,) bool.
    values : mapping, optional
        Per sensor type, the calibrated values of ``fields`` in sensor-id order (N, n), when
        the caller has them (:func:`~imufdi_cli.calibrate.noise.static_noise`).
    """
    motion = motion_rows(array, static, clipped)
    rows = motion & np.roll(motion, 1)
    out: dict[str, float] = {}
    if method == "off" or not rows[1:].any():
        return out
    alpha = JITTER_LEVEL_ALPHA if method == "level" else None
    for sensor_type, raw in fields.items():
        sigma = array.sensor_noise(sensor_type)
        if raw is None or sigma is None or array.n_sensors(sensor_type) < 4:
            continue
        design = array.measurement_matrix(sensor_type)
        if sensor_type == "accel":
            try:
                design = accel_design(array, sensor_type)
            except ArrayConfigError:
                pass
        if design.shape[0] <= design.shape[1]:
            continue
        given = None if values is None else values.get(sensor_type)
        if given is None:
            given = array.select(array.calibrate_triads(raw, sensor_type), sensor_type)
        white = given / sigma
        offset = white[static].mean(axis=0) if static.any() else None
        out[sensor_type] = fit_jitter(design / sigma[:, None], white, t_s, rows, offset, alpha)
    return out
