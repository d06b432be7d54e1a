"""cnn-map's reference rate (paper §2): array geometry, the GLT-screened least-squares body
rate with gyro exclusion and re-admission.
"""

from __future__ import annotations

from itertools import pairwise
from typing import Any

import numpy as np

from imufdi_cli.array import ArrayConfig
from imufdi_cli.detectors.cnn_map.settings import _Settings
from imufdi_cli.detectors.cnn_map.signals import READMIT_S
from imufdi_cli.errors import (
    ArrayTooSmallError,
    DetectorConfigError,
)
from imufdi_cli.log import ImuBlock
from imufdi_cli.maths.parity import least_squares_matrix


class _ReferenceRate(_Settings):
    """Geometry and the GLT-screened reference rate of :class:`CnnMapDetector`."""

    # --- geometry and reference --------------------------------------------------------

    def _setup(self, array: ArrayConfig) -> None:
        tested = [k for k, imu in enumerate(array.imus) if len(imu.axes_of("accel")) == 3]
        if len(tested) < 2:
            raise ArrayTooSmallError(
                "cnn-map compares IMUs with each other and needs at least 2 with full"
                f" accelerometer triads; this array has {len(tested)}"
            )
        if (
            array.n_sensors("gyro") < 3
            or np.linalg.matrix_rank(array.measurement_matrix("gyro")) < 3
        ):
            raise DetectorConfigError(
                "cnn-map needs gyros spanning 3 axes for the reference rate; this array has"
                f" {array.n_sensors('gyro')} gyros"
            )
        self.array = array
        self.tested = np.asarray(tested, dtype=np.intp)  # IMUs with an accel triad
        self.rotations = array.rotations()[self.tested]  # (m, 3, 3) IMU -> body
        imu_idx, axis_idx = array.sensor_index("accel")
        self.n_accel = int(imu_idx.size)
        # accel sensor index of (tested IMU position, axis)
        lookup = {(int(k), int(a)): j for j, (k, a) in enumerate(zip(imu_idx, axis_idx))}
        self.sensor_of = np.array([[lookup[(int(k), a)] for a in range(3)] for k in self.tested])
        self.gyro_H = array.measurement_matrix("gyro")
        self.gyro_ids = array.sensor_ids("gyro")
        self.excluded_gyros: list[int] = []
        self.gyro_events: list[dict[str, Any]] = []
        self._estimator = least_squares_matrix(self.gyro_H)  # (3, n_g)
        self._full_estimator = self._estimator
        self._estimators: dict[frozenset[int], np.ndarray] = {}
        # stream index of each gyro's last GLT isolation (-inf: never)
        self._last_isolated = np.full(len(self.gyro_ids), -np.inf)
        self._readmit_samples = max(1, round(READMIT_S * array.rate_hz))
        self._samples_seen = 0

    def _body_accel(self, block: ImuBlock) -> np.ndarray:
        """Specific force of the tested IMUs in the body frame, (N, m, 3), m/s^2."""
        assert block.accel is not None
        return np.einsum("kab,nkb->nka", self.rotations, block.accel[:, self.tested, :])

    def _reference_rate(self, block: ImuBlock) -> np.ndarray:
        """GLT-screened least-squares body rate (N, 3), rad/s (paper §2)."""
        assert self.array is not None and block.gyro is not None
        gyro = self.array.select(block.gyro, "gyro")
        n_samples = gyro.shape[0]
        if self._glt is None:
            return gyro @ self._estimator.T  # type: ignore[no-any-return]
        isolated = self._glt.process(ImuBlock(t_ns=block.t_ns, gyro=block.gyro))["gyro"].isolated
        # A gyro is left out of the reference while the GLT isolates it and for READMIT_S
        # after its last isolation; then it is re-admitted (a GLT false alarm must not
        # remove a healthy gyro for good). Exclusions and re-admissions are logged.
        n_gyros = len(self.gyro_ids)
        stamp = np.full((n_samples, n_gyros), -np.inf)
        hits = np.flatnonzero(isolated >= 0)
        stamp[hits, isolated[hits]] = self._samples_seen + hits
        last = np.maximum.accumulate(np.vstack([self._last_isolated[None], stamp]), axis=0)[1:]
        position = self._samples_seen + np.arange(n_samples)
        excluded = (position[:, None] - last) < self._readmit_samples  # (N, n_g)
        if n_samples:
            self._last_isolated = last[-1].copy()
        previous = np.zeros(n_gyros, dtype=bool)
        previous[self.excluded_gyros] = True
        stacked = np.vstack([previous[None], excluded])
        changes = np.flatnonzero(np.any(stacked[1:] != stacked[:-1], axis=1))
        rate = np.empty((n_samples, 3))
        bounds = [0, *changes.tolist(), n_samples]
        state = previous
        for start, stop in pairwise(bounds):
            if stop <= start:
                continue
            now = excluded[start]
            for sensor in np.flatnonzero(now & ~state):
                self.gyro_events.append(
                    {"sample": int(position[start]), "excluded": self.gyro_ids[sensor]}
                )
            for sensor in np.flatnonzero(state & ~now):
                self.gyro_events.append(
                    {"sample": int(position[start]), "readmitted": self.gyro_ids[sensor]}
                )
            state = now
            rate[start:stop] = gyro[start:stop] @ self._estimator_without(now).T
        self.excluded_gyros = np.flatnonzero(state).tolist()
        return rate

    def _estimator_without(self, excluded: np.ndarray) -> np.ndarray:
        """Least-squares rate estimator (3, n_g) of the gyros not ``excluded`` (cached); the
        full one if the rest do not span 3 axes."""
        key = frozenset(np.flatnonzero(excluded).tolist())
        if not key:
            return self._full_estimator
        if key not in self._estimators:
            active = np.flatnonzero(~excluded)
            estimator = self._full_estimator
            if active.size >= 3 and np.linalg.matrix_rank(self.gyro_H[active]) == 3:
                estimator = np.zeros((3, len(self.gyro_ids)))
                estimator[:, active] = least_squares_matrix(self.gyro_H[active])
            if len(self._estimators) > 1024:
                self._estimators.clear()
            self._estimators[key] = estimator
        return self._estimators[key]
