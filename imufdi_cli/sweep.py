"""Matched-FAR threshold sweep, streaming (docs/metrics.md).

Every status row carries the detector's statistic and threshold; their ratio
``r = statistic / threshold`` is what a threshold scale ``s`` compares against: the raw test
alarms at scale s when ``r >= s`` (s = 1 is the detector's own threshold). A row whose ratio
is undefined (NaN statistic, infinite, NaN or non-positive threshold) never alarms at any
scale. Rows are counted in fixed histograms of ``log10 r`` (bins of :data:`STEP` decades
from :data:`LOG_LOW` to :data:`LOG_HIGH`, plus one bin below and one above), so memory does
not depend on the log length:

- fault-free rows outside the calibration window (FAR),
- faulty rows outside the calibration window, split by how their isolation would be judged
  (correct / wrong / none; MAR and FIR),
- per fault, the decision time of the first row at or above each bin (detection delay).

Counts are exact at every bin edge ``s_k = 10**(LOG_LOW + k * STEP)``. The matched scale
for a target FAR f is the smallest scale whose FAR <= f: between the two edges that bracket
f, ``log10 s`` is interpolated linearly in FAR, and MAR and FIR at the same fraction of the
step; the detection delay is read at the upper (less sensitive) edge. The sweep applies to
the raw ratio only: post-processing rules of a detector (confirmation over several
samples, persistence, isolation-triggered reconfiguration) are not re-run, so the matched
figures describe the per-sample test, which the notes of the report say.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

LOG_LOW = -4.0
LOG_HIGH = 6.0
STEP = 0.01
N_BINS = round((LOG_HIGH - LOG_LOW) / STEP)
#: log10 of the scale at each edge k = 0..N_BINS.
EDGES = LOG_LOW + STEP * np.arange(N_BINS + 1)
NS_PER_S = 1_000_000_000


def ratio_bins(statistic: np.ndarray, threshold: np.ndarray) -> np.ndarray:
    """Histogram bin of each row's ``statistic / threshold``.

    Bin 0 holds ratios below ``10**LOG_LOW`` (and undefined ratios), bin i in 1..N_BINS
    holds ``EDGES[i-1] <= log10 r < EDGES[i]``, bin N_BINS + 1 the ratios at or above
    ``10**LOG_HIGH``. A row alarms at edge k (``r >= 10**EDGES[k]``) iff its bin > k.

    Returns
    -------
    ndarray, shape (N,), int64
    """
    statistic = np.asarray(statistic, dtype=np.float64)
    threshold = np.asarray(threshold, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        ratio = statistic / threshold
    valid = np.isfinite(threshold) & (threshold > 0) & ~np.isnan(statistic) & (ratio > 0)
    logs = np.full(ratio.shape, -np.inf)
    logs[valid] = np.log10(ratio[valid])
    index = np.zeros(ratio.shape, dtype=np.int64)
    finite = np.isfinite(logs)
    index[finite] = np.clip(
        np.floor((logs[finite] - LOG_LOW) / STEP).astype(np.int64) + 1, 0, N_BINS + 1
    )
    index[np.isposinf(logs)] = N_BINS + 1
    return index


def _at_or_above(counts: np.ndarray) -> np.ndarray:
    """(N_BINS + 1,) rows alarming at each edge k: the count of bins > k."""
    tail = np.cumsum(counts[::-1])[::-1]  # tail[i] = sum of counts[i:]
    return tail[1:]


@dataclass
class MatchedFar:
    """Figures at a matched false-alarm rate (one detector, one sensor type)."""

    target_far: float
    far: float | None  # FAR at the matched scale (interpolated, equals the target)
    threshold_scale: float | None  # matched threshold / the detector's own threshold
    mar: float | None
    fir: float | None
    detection_delay_s: float | None
    note: str | None = None

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


class SweepAccumulator:
    """Streaming histograms for the matched-FAR sweep of one detector and sensor type.

    Parameters
    ----------
    fault_starts_ns : sequence of int
        Onset of each fault (same order as the rows' per-fault masks passed to update).
    """

    def __init__(self, fault_starts_ns: Sequence[int] = ()) -> None:
        size = N_BINS + 2
        self.free = np.zeros(size, dtype=np.int64)
        self.correct = np.zeros(size, dtype=np.int64)
        self.wrong = np.zeros(size, dtype=np.int64)
        self.none = np.zeros(size, dtype=np.int64)
        self.starts = [int(s) for s in fault_starts_ns]
        #: per fault: first decision time (ns) of a row in bin >= level, -1 when none yet
        self.first = [np.full(size, -1, dtype=np.int64) for _ in self.starts]
        self._level = [0 for _ in self.starts]
        self.undefined_rows = 0
        self.rows = 0

    def update(
        self,
        bins: np.ndarray,
        decided_ns: np.ndarray,
        free: np.ndarray,
        iso_class: np.ndarray,
        in_fault: Sequence[np.ndarray],
    ) -> None:
        """Add rows.

        Parameters
        ----------
        bins : (k,) int64, from :func:`ratio_bins`
        decided_ns : (k,) int64, decision times
        free : (k,) bool, fault-free rows to count for FAR (outside calibration)
        iso_class : (k,) int8, for faulty rows to count: 1 correct, 2 wrong, 3 no
            isolation; 0 for rows not counted
        in_fault : per fault, (k,) bool rows inside the fault's window
        """
        self.rows += int(bins.size)
        self.undefined_rows += int(np.count_nonzero(bins == 0))
        size = N_BINS + 2
        self.free += np.bincount(bins[free], minlength=size)
        for cls, hist in ((1, self.correct), (2, self.wrong), (3, self.none)):
            hist += np.bincount(bins[iso_class == cls], minlength=size)
        for f, mask in enumerate(in_fault):
            rows = np.flatnonzero(mask)
            if rows.size == 0:
                continue
            level = self._level[f]
            b = bins[rows]
            peak = np.maximum.accumulate(b)
            rising = np.flatnonzero(peak > np.concatenate([[level], peak[:-1]]))
            for j in rising.tolist():
                new = int(peak[j])
                if new > level:
                    self.first[f][level + 1 : new + 1] = decided_ns[rows[j]]
                    level = new
            self._level[f] = level

    @property
    def sweepable(self) -> bool:
        """Whether any counted row has a defined ratio."""
        counted = self.free.sum() + self.correct.sum() + self.wrong.sum() + self.none.sum()
        defined = counted - (self.free[0] + self.correct[0] + self.wrong[0] + self.none[0])
        return bool(counted) and bool(defined)

    def curve(self) -> dict[str, np.ndarray]:
        """FAR, MAR, FIR and mean detection delay at every edge (arrays of N_BINS + 1).

        Undefined values are NaN.
        """
        n_free = int(self.free.sum())
        faulty = self.correct + self.wrong + self.none
        n_faulty = int(faulty.sum())
        with np.errstate(invalid="ignore", divide="ignore"):
            far = _at_or_above(self.free) / n_free if n_free else np.full(N_BINS + 1, np.nan)
            detected = _at_or_above(faulty)
            mar = (n_faulty - detected) / n_faulty if n_faulty else np.full(N_BINS + 1, np.nan)
            fir = np.where(detected > 0, _at_or_above(self.wrong) / np.maximum(detected, 1), np.nan)
        delays = np.full(N_BINS + 1, np.nan)
        if self.starts:
            per_fault = np.full((len(self.starts), N_BINS + 1), np.nan)
            for f, start in enumerate(self.starts):
                first = self.first[f][1:]  # alarming at edge k = first row in bin >= k + 1
                hit = first >= 0
                per_fault[f, hit] = (first[hit] - start) / NS_PER_S
            with np.errstate(invalid="ignore"):
                counts = np.sum(~np.isnan(per_fault), axis=0)
                sums = np.nansum(per_fault, axis=0)
                delays = np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)
        return {
            "log10_scale": EDGES.copy(),
            "far": far,
            "mar": mar,
            "fir": fir,
            "detection_delay_s": delays,
        }

    def match(self, target: float) -> MatchedFar:
        """Figures at the smallest threshold scale whose FAR <= ``target``."""
        empty = MatchedFar(target, None, None, None, None, None)
        if not self.sweepable:
            empty.note = "no sweepable statistic (statistic/threshold undefined on every row)"
            return empty
        curve = self.curve()
        far = curve["far"]
        if np.isnan(far).all():
            empty.note = "no fault-free samples outside the calibration window"
            return empty
        ok = np.flatnonzero(far <= target)
        if ok.size == 0:
            empty.note = f"FAR stays above {target:g} up to {10**LOG_HIGH:g} x the threshold"
            return empty
        k = int(ok[0])

        def value(name: str, w: float) -> float | None:
            hi = curve[name][k]
            if k == 0 or w >= 1.0:
                return None if np.isnan(hi) else float(hi)
            lo = curve[name][k - 1]
            if np.isnan(lo) or np.isnan(hi):
                return None if np.isnan(hi) else float(hi)
            return float(lo + w * (hi - lo))

        if k == 0:
            w = 1.0
            note = f"FAR <= {target:g} already at {10**LOG_LOW:g} x the threshold (range bottom)"
        else:
            drop = far[k - 1] - far[k]
            w = float((far[k - 1] - target) / drop) if drop > 0 else 1.0
            note = None
        log_scale = EDGES[k] if k == 0 else EDGES[k - 1] + w * STEP
        delay = curve["detection_delay_s"][k]
        return MatchedFar(
            target_far=target,
            far=value("far", w),
            threshold_scale=float(10**log_scale),
            mar=value("mar", w),
            fir=value("fir", w),
            detection_delay_s=None if np.isnan(delay) else float(delay),
            note=note,
        )
