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
    #: its rows ``first_row:end_row`` of the log (-1: not known, found from the times)
    first_row: int = -1
    end_row: int = -1

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
    """Static intervals (and their row mask) of raw accel (N, m, 3), gyro (N, m, 3) in
    memory: :class:`StaticScan` fed once."""
    scan = StaticScan(array, gyro is not None, min_static_s=min_static_s)
    try:
        scan.add(t_s, accel, gyro, usable)
        intervals = scan.finish()
    finally:
        scan.close()
    mask = np.zeros(len(t_s), dtype=bool)
    for item in intervals:
        mask[item.first_row : item.end_row] = True
    return intervals, mask


class StaticScan:
    """The static intervals of a log streamed block by block, in bounded memory.

    Per sensor type (accelerometers, gyros if any) the body-frame array consensus of the
    usable rows is taken; its centred moving standard deviation over
    :data:`STATIC_WINDOW_S` (:class:`~imufdi_cli.calibrate.passes.MovingStd`) must stay
    under :data:`STATIC_FLOOR_FACTOR` times its own 10th percentile over the usable rows
    (the noise floor; exact, :func:`~imufdi_cli.calibrate.passes.percentile`), with the
    absolute caps of :data:`STATIC_CAP`, for at least ``min_static_s``; each run of such
    rows is trimmed by another half window at each end. The per-row values are kept in
    temporary files (:class:`~imufdi_cli.calibrate.passes.Spool`) until :meth:`finish`.
    """

    def __init__(self, array: ArrayConfig, has_gyro: bool, *, min_static_s: float = 5.0) -> None:
        from imufdi_cli.calibrate.passes import MovingStd, Spool

        self.array = array
        self.min_static_s = min_static_s
        self.w = max(3, round(STATIC_WINDOW_S * array.rate_hz))
        self.types = ["accel", "gyro"] if has_gyro else ["accel"]
        self.moving = {s: MovingStd(self.w) for s in self.types}
        self.spread = {s: Spool(np.float64) for s in self.types}
        self.t_s = Spool(np.float64)
        self.usable = Spool(np.bool_)
        self.consensus = Spool(np.float64, (3,))  # accelerometers, the interval directions

    def add(
        self, t_s: np.ndarray, accel: np.ndarray, gyro: np.ndarray | None, usable: np.ndarray
    ) -> None:
        """The next rows: times (k,) s, raw accel and gyro (k, m, 3), usable (k,) bool."""
        for name, data in (("accel", accel), ("gyro", gyro)):
            if name not in self.types:
                continue
            assert data is not None
            consensus = body_consensus(self.array, np.where(usable[:, None, None], data, 0.0))
            if name == "accel":
                # each row of the consensus is its own row's sum: on usable rows (the only
                # ones read: intervals lie in them) it is the consensus of ``accel``
                self.consensus.append(consensus)
            self.spread[name].append(self.moving[name].feed(consensus))
        self.t_s.append(np.asarray(t_s, np.float64))
        self.usable.append(np.asarray(usable, bool))

    def finish(self) -> list[StaticInterval]:
        """The static intervals, with their rows (``first_row``, ``end_row``)."""
        from imufdi_cli.calibrate.passes import Spool, percentile, spool_chunks

        limits = {}
        for name in self.types:
            self.spread[name].append(self.moving[name].finish())
            kept = Spool(np.float64)
            try:
                for spread, ok in spool_chunks((self.spread[name], self.usable)):
                    kept.append(spread[ok])
                floor = percentile(kept, 10) if len(kept) else 0.0
            finally:
                kept.close()
            limits[name] = min(STATIC_CAP[name], max(STATIC_FLOOR_FACTOR * floor, 1e-12))
        # runs of still rows (the centred window already keeps w/2 off a move), trimmed by
        # another half window at each end
        intervals: list[StaticInterval] = []
        spools = (self.usable, *(self.spread[name] for name in self.types))
        run_start: int | None = None
        previous = False
        position = 0
        for chunk in spool_chunks(spools):
            usable_rows, spreads = chunk[0], chunk[1:]
            still = usable_rows.copy()
            for name, spread in zip(self.types, spreads):
                still &= spread < limits[name]
            before = np.concatenate([[previous], still[:-1]])
            starts = np.flatnonzero(still & ~before) + position
            ends = np.flatnonzero(~still & before) + position
            for row, is_start in sorted(
                [(r, True) for r in starts.tolist()] + [(r, False) for r in ends.tolist()]
            ):
                if is_start:
                    run_start = row
                else:
                    assert run_start is not None
                    self._interval(run_start, row, intervals)
                    run_start = None
            if still.size:
                previous = bool(still[-1])
            position += still.size
        if run_start is not None:
            self._interval(run_start, position, intervals)
        return intervals

    def _interval(self, start: int, end: int, intervals: list[StaticInterval]) -> None:
        """The interval of the still run ``start:end``, if it lasts long enough."""
        a, b = start + self.w // 2, end - self.w // 2
        if b <= a:
            return
        t_a, t_b = float(self.t_s.read(a, a + 1)[0]), float(self.t_s.read(b - 1, b)[0])
        if t_b - t_a < self.min_static_s:
            return
        from imufdi_cli.calibrate.passes import SPOOL_CHUNK

        if b - a <= SPOOL_CHUNK:  # in one piece: the mean numpy takes of the rows
            mean = self.consensus.read(a, b).mean(axis=0)
        else:
            total = np.zeros(3)
            for lo in range(a, b, SPOOL_CHUNK):
                total += self.consensus.read(lo, min(lo + SPOOL_CHUNK, b)).sum(axis=0)
            mean = total / (b - a)
        norm = np.linalg.norm(mean)
        if not np.isfinite(norm) or norm == 0:
            return
        intervals.append(StaticInterval(t_a, t_b, mean / norm, first_row=a, end_row=b))

    def close(self) -> None:
        for spool in (*self.spread.values(), self.t_s, self.usable, self.consensus):
            spool.close()


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
