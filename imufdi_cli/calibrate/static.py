"""Static intervals of a calibration log: where the array rests, and in which orientation."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from imufdi_cli.array import ArrayConfig

STANDARD_GRAVITY = 9.80665  # m/s^2
#: Static detection: window (s), noise-floor multiple and absolute caps (SI).
STATIC_WINDOW_S = 1.0
STATIC_FLOOR_FACTOR = 3.0
STATIC_CAP = {"accel": 0.3, "gyro": np.radians(3.0)}
#: Two static intervals are the same orientation when their gravity directions are closer.
SAME_ORIENTATION_RAD = np.radians(10.0)


@dataclass
class StaticInterval:
    start_s: float
    end_s: float
    direction: np.ndarray  # unit gravity-opposite direction (specific force), body frame
    orientation: int = -1

    def to_dict(self) -> dict[str, Any]:
        return {
            "start_s": round(self.start_s, 3),
            "end_s": round(self.end_s, 3),
            "direction": [round(float(v), 4) for v in self.direction],
            "orientation": self.orientation,
        }


def _moving_std(x: np.ndarray, w: int) -> np.ndarray:
    """Centred moving standard deviation (N,) of the rows of x (N, 3), summed over axes."""
    n = x.shape[0]
    w = max(2, min(w, n))
    c1 = np.concatenate([np.zeros((1, 3)), np.cumsum(x, axis=0)])
    c2 = np.concatenate([np.zeros((1, 3)), np.cumsum(x * x, axis=0)])
    lo = np.clip(np.arange(n) - w // 2, 0, n - w)
    hi = lo + w
    mean = (c1[hi] - c1[lo]) / w
    var = (c2[hi] - c2[lo]) / w - mean * mean
    return np.sqrt(np.maximum(var, 0.0).sum(axis=1))


def body_consensus(array: ArrayConfig, triads: np.ndarray) -> np.ndarray:
    """Mean over IMUs of ``R_k x_k``: (N, m, 3) -> (N, 3) in the body frame."""
    return np.einsum("kij,nkj->ni", array.rotations(), triads) / triads.shape[1]


def find_static(
    array: ArrayConfig,
    accel: np.ndarray,
    gyro: np.ndarray | None,
    t_s: np.ndarray,
    usable: np.ndarray,
    *,
    min_static_s: float = 5.0,
) -> tuple[list[StaticInterval], np.ndarray]:
    """Static intervals (and their row mask) of raw accel (N, m, 3), gyro (N, m, 3)."""
    rate = array.rate_hz
    w = max(3, round(STATIC_WINDOW_S * rate))
    still = usable.copy()
    consensus_a = np.zeros((len(t_s), 3))
    for name, data in (("accel", accel), ("gyro", gyro)):
        if data is None:
            continue
        consensus = body_consensus(array, np.where(usable[:, None, None], data, 0.0))
        if name == "accel":
            # each row of the consensus is its own row's sum: on usable rows (the only ones
            # read below: intervals lie in ``still``) it is the consensus of ``accel``
            consensus_a = consensus
        spread = _moving_std(consensus, w)
        floor = float(np.percentile(spread[usable], 10)) if usable.any() else 0.0
        still &= spread < min(STATIC_CAP[name], max(STATIC_FLOOR_FACTOR * floor, 1e-12))
    # runs of still rows (the centred window already keeps w/2 off a move), trimmed by
    # another half window at each end
    mask = np.zeros(len(t_s), dtype=bool)
    intervals: list[StaticInterval] = []
    edges = np.flatnonzero(np.diff(np.concatenate([[0], still.astype(np.int8), [0]])))
    for a, b in zip(edges[::2], edges[1::2]):
        a, b = a + w // 2, b - w // 2
        if b <= a or t_s[b - 1] - t_s[a] < min_static_s:
            continue
        mean = consensus_a[a:b].mean(axis=0)
        norm = np.linalg.norm(mean)
        if not np.isfinite(norm) or norm == 0:
            continue
        intervals.append(StaticInterval(float(t_s[a]), float(t_s[b - 1]), mean / norm))
        mask[a:b] = True
    return intervals, mask


def group_orientations(intervals: list[StaticInterval]) -> tuple[int, float]:
    """Assign orientation numbers in place; returns (count, coverage in [0, 1])."""
    centres: list[np.ndarray] = []
    for item in intervals:
        for j, c in enumerate(centres):
            if np.arccos(np.clip(c @ item.direction, -1, 1)) < SAME_ORIENTATION_RAD:
                item.orientation = j
                break
        else:
            item.orientation = len(centres)
            centres.append(item.direction)
    if not centres:
        return 0, 0.0
    u = np.stack(centres)
    scatter = u.T @ u / len(u)
    return len(centres), max(0.0, float(3.0 * np.linalg.eigvalsh(scatter)[0]))


# --- estimation ------------------------------------------------------------------------
