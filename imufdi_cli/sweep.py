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

import math
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


def best_columns(scores: np.ndarray) -> np.ndarray:
    """The column of each row's first largest finite score, -1 where none is finite: the
    sensor a row the detector left unisolated is judged isolated to at any threshold
    (:func:`imufdi_cli.metrics.rows.judged_isolation`).

    Parameters
    ----------
    scores : ndarray, shape (k, n), float64
        Isolation scores (any strides: a view into the status payloads is read in place).

    Returns
    -------
    ndarray, shape (k,), int64
    """
    k, n = scores.shape
    if n == 0:
        return np.full(k, -1, np.int64)
    # argmax of the scores themselves is the answer where the score it picks is finite
    # (then no NaN or +inf comes before it, and -inf never wins); the other rows (NaN,
    # +inf, or nothing finite) take the masked argmax: one pass over the scores, not three
    best = np.argmax(scores, axis=1).astype(np.int64, copy=False)
    odd = np.flatnonzero(~np.isfinite(scores[np.arange(k), best]))
    if odd.size:
        part = np.asarray(scores[odd], dtype=np.float64)
        masked = np.where(np.isfinite(part), part, -np.inf)
        column = np.argmax(masked, axis=1)
        best[odd] = np.where(masked[np.arange(odd.size), column] > -np.inf, column, -1)
    return best


def _first_at_levels(
    first: np.ndarray, level: int, bins: np.ndarray, decided_ns: np.ndarray, mask: np.ndarray
) -> int:
    """Record in ``first`` (per bin level) the decision time of the first row of ``mask``
    reaching each level above ``level`` (the highest reached so far); returns the new
    highest level."""
    rows = np.flatnonzero(mask)
    if rows.size == 0:
        return level
    b = bins[rows]
    peak = np.maximum.accumulate(b)
    rising = np.flatnonzero(peak > np.concatenate([[level], peak[:-1]]))
    for j in rising.tolist():
        new = int(peak[j])
        if new > level:
            first[level + 1 : new + 1] = decided_ns[rows[j]]
            level = new
    return level


def _mean_delays(first: Sequence[np.ndarray], starts: Sequence[int]) -> np.ndarray:
    """(N_BINS + 1,) mean over faults of the delay (s) to the first row at each edge (a
    fault not reached there left out; NaN when none is)."""
    if not starts:
        return np.full(N_BINS + 1, np.nan)
    per_fault = np.full((len(starts), N_BINS + 1), np.nan)
    for f, start in enumerate(starts):
        at = first[f][1:]  # alarming at edge k = first row in bin >= k + 1
        hit = at >= 0
        per_fault[f, hit] = (at[hit] - start) / NS_PER_S
    counts = np.sum(~np.isnan(per_fault), axis=0)
    sums = np.nansum(per_fault, axis=0)
    return np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)


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
        #: the same for the rows isolated to one of the fault's sensors (isolation delay)
        self.first_isolated = [np.full(size, -1, dtype=np.int64) for _ in self.starts]
        self._level_isolated = [0 for _ in self.starts]
        self.undefined_rows = 0
        self.rows = 0
        self._curve: dict[str, np.ndarray] | None = None  # curve() of the rows so far

    def update(
        self,
        bins: np.ndarray,
        decided_ns: np.ndarray,
        free: np.ndarray,
        iso_class: np.ndarray,
        in_fault: Sequence[np.ndarray],
        isolated_to: Sequence[np.ndarray] | None = None,
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
        isolated_to : per fault, (k,) bool rows inside it isolated (or, unisolated, judged
            by their largest score) to one of its sensors (isolation delays)
        """
        self._curve = None
        self.rows += int(bins.size)
        self.undefined_rows += int(np.count_nonzero(bins == 0))
        size = N_BINS + 2
        self.free += np.bincount(bins[free], minlength=size)
        for cls, hist in ((1, self.correct), (2, self.wrong), (3, self.none)):
            hist += np.bincount(bins[iso_class == cls], minlength=size)
        for f, mask in enumerate(in_fault):
            self._level[f] = _first_at_levels(self.first[f], self._level[f], bins, decided_ns, mask)
        for f, mask in enumerate(isolated_to or ()):
            self._level_isolated[f] = _first_at_levels(
                self.first_isolated[f], self._level_isolated[f], bins, decided_ns, mask
            )

    @property
    def sweepable(self) -> bool:
        """Whether any counted row has a defined ratio."""
        counted = self.free.sum() + self.correct.sum() + self.wrong.sum() + self.none.sum()
        defined = counted - (self.free[0] + self.correct[0] + self.wrong[0] + self.none[0])
        return bool(counted) and bool(defined)

    def curve(self) -> dict[str, np.ndarray]:
        """FAR, MAR, FIR and mean detection delay at every edge (arrays of N_BINS + 1).

        Undefined values are NaN. (Computed once per state of the histograms: do not
        modify the arrays.)
        """
        if self._curve is None:
            self._curve = self._compute_curve()
        return self._curve

    def _compute_curve(self) -> dict[str, np.ndarray]:
        n_free = int(self.free.sum())
        faulty = self.correct + self.wrong + self.none
        n_faulty = int(faulty.sum())
        with np.errstate(invalid="ignore", divide="ignore"):
            far = _at_or_above(self.free) / n_free if n_free else np.full(N_BINS + 1, np.nan)
            detected = _at_or_above(faulty)
            mar = (n_faulty - detected) / n_faulty if n_faulty else np.full(N_BINS + 1, np.nan)
            fir = np.where(detected > 0, _at_or_above(self.wrong) / np.maximum(detected, 1), np.nan)
        delays = _mean_delays(self.first, self.starts)
        isolation = _mean_delays(self.first_isolated, self.starts)
        return {
            "log10_scale": EDGES.copy(),
            "far": far,
            "mar": mar,
            "fir": fir,
            "detection_delay_s": delays,
            "isolation_delay_s": isolation,
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


# --- alarm episodes at many levels ------------------------------------------------------

#: Largest gap in rows, a sentinel "no alarm yet" position (far before any row).
_NEVER = -(1 << 62)


class AlarmEpisodes:
    """Alarm episodes under the joining rule of :mod:`imufdi_cli.episodes.builder`, counted
    at L alarm levels at once, streaming (memory: L x n, whatever the log length).

    The rule, on the status rows of one channel: alarmed rows separated by at most
    ``merge_gap`` quiet rows are one *run*; a run's sensor is the one it isolated on most
    of its alarmed rows (the lowest index on ties; none when no row isolated a sensor); a
    run with a sensor *joins* the episode of the previous run with the same sensor when
    at most ``join_gap`` rows separate the first row of the new run from the last alarmed
    row of the previous one. An episode starts at the first alarmed row of its first run;
    it is counted (``episodes``) and, when that row is *eligible* (for the false-alarm
    figures: tested, scored, fault-free and outside the calibration window), counted as
    false (``false_episodes``). The builder explains each such episode; this class only
    counts them, for the ``false_episodes_per_hour`` of docs/metrics.md and, at scaled
    thresholds, for the matched budget.

    Parameters
    ----------
    levels : int
        L: feed an (L, k) alarm matrix per block (row l: the alarms at level l).
    n_sensors : int
    merge_gap, join_gap : int
        Rows (:func:`episode_gap_rows`).
    """

    def __init__(self, levels: int, n_sensors: int, merge_gap: int, join_gap: int) -> None:
        self.levels = int(levels)
        self.n = max(int(n_sensors), 1)
        self.merge_gap = int(merge_gap)
        self.join_gap = int(join_gap)
        self.rows = 0  # rows fed so far (global row index of the next row)
        self.episodes = np.zeros(self.levels, np.int64)
        self.false_episodes = np.zeros(self.levels, np.int64)
        # the open run of each level (its last alarm at most merge_gap rows before now)
        self.open = np.zeros(self.levels, bool)
        self.open_start = np.zeros(self.levels, np.int64)
        self.open_last = np.full(self.levels, _NEVER, np.int64)
        self.open_eligible = np.zeros(self.levels, bool)
        self.open_counts = np.zeros((self.levels, self.n), np.int64)
        # per level and sensor: the last alarmed row of the last run with that sensor
        self.last_end = np.full((self.levels, self.n), _NEVER, np.int64)

    def update(self, alarm: np.ndarray, isolated: np.ndarray, eligible: np.ndarray) -> None:
        """The next k rows.

        Parameters
        ----------
        alarm : (L, k) bool, the alarms at each level (or (k,) when L = 1)
        isolated : (k,) int, each row's isolated sensor (outside 0..n-1: none)
        eligible : (k,) bool, whether an episode starting on the row counts as false
        """
        isolated = np.asarray(isolated, np.int64)
        k = int(isolated.size)
        if k == 0:
            return
        alarm = np.asarray(alarm, bool).reshape(self.levels, k)
        level, column = np.nonzero(alarm)
        self._rows(level, column, isolated, np.asarray(eligible, bool), k)

    def update_sparse(
        self,
        level: np.ndarray,
        column: np.ndarray,
        isolated: np.ndarray,
        eligible: np.ndarray,
        k: int,
    ) -> None:
        """The next k rows, given as their alarms: ``(level[i], column[i])`` for every
        alarmed (level, row) pair, sorted by level then row (``np.nonzero`` of the (L, k)
        matrix); ``isolated`` and ``eligible`` of shape (k,) as in :meth:`update`."""
        if k:
            self._rows(level, column, np.asarray(isolated, np.int64), eligible, int(k))

    def _rows(
        self,
        lev: np.ndarray,
        col: np.ndarray,
        isolated: np.ndarray,
        eligible: np.ndarray,
        k: int,
    ) -> None:
        g0 = self.rows
        end = g0 + k - 1  # the last row of the block
        self.rows += k
        lev = np.asarray(lev, np.int64)
        pos = g0 + np.asarray(col, np.int64)
        m = int(pos.size)
        if m == 0:
            # no alarm at any level: open runs that are now followed by merge_gap quiet rows end
            self._close_carried(self.open & (end - self.open_last > self.merge_gap))
            return
        first = np.ones(m, bool)
        first[1:] = lev[1:] != lev[:-1]
        previous = np.empty(m, np.int64)
        previous[1:] = pos[:-1]
        previous[first] = np.where(self.open[lev[first]], self.open_last[lev[first]], _NEVER)
        new_run = pos - previous - 1 > self.merge_gap
        boundary = new_run | first
        segment = np.cumsum(boundary) - 1
        heads = np.flatnonzero(boundary)
        seg_level = lev[heads]
        continued = ~new_run[heads]  # a level's first segment continuing its open run
        # the open runs that this block ends: a level whose first alarm here starts a new
        # run, or without alarms here and merge_gap quiet rows after its last one
        present = np.zeros(self.levels, bool)
        present[seg_level] = True
        starts_new = np.zeros(self.levels, bool)
        starts_new[lev[first]] = new_run[first]
        self._close_carried(
            self.open
            & ((present & starts_new) | (~present & (end - self.open_last > self.merge_gap)))
        )
        n_seg = heads.size
        seg_start = pos[heads]
        seg_eligible = eligible[col[heads]]
        tails = np.append(heads[1:], m) - 1
        seg_last = pos[tails]
        # the last segment of each level stays open unless merge_gap quiet rows follow it
        last_of_level = np.append(seg_level[1:] != seg_level[:-1], True)
        stays = last_of_level & (end - seg_last <= self.merge_gap)
        # each segment's sensor: a one-row segment's own; the others' (and those carried
        # on from, or left open for, the next block) from their counts per sensor, taken
        # only for them (most segments of the low levels are single rows)
        iso = isolated[col]
        valid = (iso >= 0) & (iso < self.n)
        sensor = np.where(valid[heads], iso[heads], -1)
        counted = (tails > heads) | continued | stays
        dense = np.flatnonzero(counted)
        counts = np.zeros((dense.size, self.n), np.int64)
        if dense.size:
            compact = np.full(n_seg, -1, np.int64)
            compact[dense] = np.arange(dense.size)
            where = compact[segment]
            use = valid & (where >= 0)
            counts = np.bincount(
                where[use] * self.n + iso[use], minlength=dense.size * self.n
            ).reshape(dense.size, self.n)
            carried_rows = continued[dense]
            if carried_rows.any():
                carried = seg_level[dense[carried_rows]]
                counts[carried_rows] += self.open_counts[carried]
            sensor[dense] = np.where(counts.any(axis=1), np.argmax(counts, axis=1), -1)
        if continued.any():
            carried = seg_level[continued]
            seg_start[continued] = self.open_start[carried]
            seg_eligible[continued] = self.open_eligible[carried]
        self.open[present] = False
        staying = seg_level[stays]
        self.open[staying] = True
        self.open_start[staying] = seg_start[stays]
        self.open_last[staying] = seg_last[stays]
        self.open_eligible[staying] = seg_eligible[stays]
        self.open_counts[staying] = counts[stays[dense]] if dense.size else 0
        done = ~stays
        self._close(
            seg_level[done], seg_start[done], seg_last[done], seg_eligible[done], sensor[done]
        )

    def _close_carried(self, which: np.ndarray) -> None:
        """End the open runs of the levels ``which`` (L,) bool."""
        levels = np.flatnonzero(which)
        if levels.size:
            counts = self.open_counts[levels]
            sensor = np.where(counts.any(axis=1), np.argmax(counts, axis=1), -1)
            self._close(
                levels,
                self.open_start[levels],
                self.open_last[levels],
                self.open_eligible[levels],
                sensor,
            )
            self.open[levels] = False

    def _close(
        self,
        level: np.ndarray,
        start: np.ndarray,
        last: np.ndarray,
        eligible: np.ndarray,
        sensor: np.ndarray,
    ) -> None:
        """Ended runs (in time order within each level) with their sensor (-1: none):
        joined to their sensor's previous run or counted as new episodes."""
        if level.size == 0:
            return
        has = sensor >= 0
        joined = np.zeros(level.size, bool)
        mine = np.flatnonzero(has)
        if mine.size:
            # runs grouped by (level, sensor), in time order within each group
            order = mine[np.lexsort((start[mine], sensor[mine], level[mine]))]
            key = level[order] * self.n + sensor[order]
            group_first = np.ones(order.size, bool)
            group_first[1:] = key[1:] != key[:-1]
            before = np.empty(order.size, np.int64)
            before[1:] = last[order][:-1]
            before[group_first] = self.last_end[
                level[order][group_first], sensor[order][group_first]
            ]
            joined[order] = start[order] - before - 1 <= self.join_gap
            group_last = np.append(group_first[1:], True)
            self.last_end[level[order][group_last], sensor[order][group_last]] = last[order][
                group_last
            ]
        new = ~joined
        np.add.at(self.episodes, level[new], 1)
        np.add.at(self.false_episodes, level[new & eligible], 1)

    def finish(self) -> None:
        """End every open run (at the end of the log)."""
        self._close_carried(self.open.copy())

    def finished(self) -> AlarmEpisodes:
        """A copy with every open run ended: the counts if the log ended here (this one
        goes on)."""
        done = AlarmEpisodes.__new__(AlarmEpisodes)
        done.__dict__ = {
            k: v.copy() if isinstance(v, np.ndarray) else v for k, v in self.__dict__.items()
        }
        done.finish()
        return done


class FaultRuns:
    """Which alarmed rows belong to a run of the detector's own alarms (the merge rule of
    :class:`AlarmEpisodes`) that began on a faulty row, streaming.

    At a scaled threshold such a row's alarm belongs to that fault: a sequential statistic
    that grew inside the fault crosses a higher threshold later, after the fault's end,
    while the detector's own episode of it is still open; it is never a false episode.

    Parameters
    ----------
    merge_gap : int
        Rows.
    """

    def __init__(self, merge_gap: int) -> None:
        self.merge_gap = int(merge_gap)
        self.rows = 0
        self.last = _NEVER  # the last alarmed row so far
        self.faulty = False  # whether the run it belongs to began on a faulty row

    def update(self, alarm: np.ndarray, faulty: np.ndarray) -> np.ndarray:
        """The next k rows' own alarms and whether each is faulty; returns (k,) bool: the
        alarmed rows of runs that began on a faulty row."""
        alarm = np.asarray(alarm, bool)
        out = np.zeros(alarm.size, bool)
        at = np.flatnonzero(alarm)
        if at.size:
            rows = self.rows + at
            previous = np.concatenate([[self.last], rows[:-1]])
            new = rows - previous - 1 > self.merge_gap
            run = np.cumsum(new)  # 0: the run carried on from the previous rows
            began_faulty = np.concatenate([[self.faulty], np.asarray(faulty, bool)[at[new]]])
            out[at] = began_faulty[run]
            self.last = int(rows[-1])
            self.faulty = bool(began_faulty[-1])
        self.rows += int(alarm.size)
        return out


def episode_gap_rows(rate_hz: float, merge_gap_s: float, join_gap_s: float) -> tuple[int, int]:
    """The joining rule's gaps in rows at ``rate_hz``, as the episode builder rounds them:
    ``(merge_gap, join_gap)`` with ``join_gap >= merge_gap``."""
    merge = max(0, round(merge_gap_s * rate_hz))
    return merge, max(merge, round(join_gap_s * rate_hz))


# --- the matched false-alarm budget -----------------------------------------------------

#: Threshold scales of the matched budget: 10**-0.2 (0.63) to 10**3 of the detector's own
#: threshold, every fifth edge of the grid (0.05 decade, 12 % apart). Each level costs the
#: joining rule on every row above it, so the range is what a match can need: a per-sample
#: test is matched to 1/h above its own threshold (at alpha = 1 %, 2 to 3 x), a sequential
#: one near it (0.8 to 1.5 x between budgets 10 x apart).
BUDGET_LOG_LOW = -0.2
BUDGET_LOG_HIGH = 3.0
BUDGET_STRIDE = 5
BUDGET_LEVELS = np.arange(
    round((BUDGET_LOG_LOW - LOG_LOW) / STEP),
    round((BUDGET_LOG_HIGH - LOG_LOW) / STEP) + 1,
    BUDGET_STRIDE,
)
#: log10 of the scale at each budget level.
BUDGET_LOG_SCALES = EDGES[BUDGET_LEVELS]
#: The figures of a budget curve, besides the false episodes (undefined: NaN).
BUDGET_FIGURES = ("mar", "fir", "detection_delay_s", "isolation_delay_s")


@dataclass
class BudgetCurve:
    """One channel's figures (or a campaign's, pooled) at every budget level: the false
    alarm episodes an alarm at ``statistic >= scale x threshold`` raises (the joining rule
    of :class:`AlarmEpisodes`), the fault-free tested hours they are counted over, and
    MAR, FIR, mean detection and isolation delays at each scale (NaN: undefined).

    Attributes
    ----------
    hours : float
    false_episodes : ndarray, shape (L,), int64
    figures : dict of ndarray, shape (L,), float64
        :data:`BUDGET_FIGURES`.
    """

    hours: float
    false_episodes: np.ndarray
    figures: dict[str, np.ndarray]

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready, compact: trailing zero counts and wholly undefined figures dropped."""
        counts = self.false_episodes
        nonzero = np.flatnonzero(counts)
        kept = counts[: int(nonzero[-1]) + 1] if nonzero.size else counts[:0]
        out: dict[str, Any] = {"hours": self.hours, "false_episodes": kept.tolist()}
        for name, values in self.figures.items():
            if not np.isnan(values).all():
                out[name] = [None if np.isnan(v) else float(v) for v in values.tolist()]
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> BudgetCurve:
        """The inverse of :meth:`to_dict`."""
        size = BUDGET_LEVELS.size
        counts = np.zeros(size, np.int64)
        kept = np.asarray(data.get("false_episodes", []), np.int64)[:size]
        counts[: kept.size] = kept
        figures = {}
        for name in BUDGET_FIGURES:
            values = data.get(name)
            figures[name] = (
                np.full(size, np.nan)
                if values is None
                else np.array([np.nan if v is None else float(v) for v in values], float)
            )
        return cls(float(data.get("hours", 0.0)), counts, figures)


@dataclass
class BudgetMatch:
    """Where a budget curve meets a target rate of false episodes per hour: between levels
    ``index - 1`` and ``index`` at the fraction ``weight`` (1: at ``index``), threshold
    ``scale`` x the detector's own; None when it does not (``note`` says why)."""

    target_per_hour: float
    index: int | None = None
    weight: float = 1.0
    scale: float | None = None
    note: str | None = None


def match_budget(false_episodes: np.ndarray, hours: float, target_per_hour: float) -> BudgetMatch:
    """The smallest threshold scale above which the false-episode rate stays at or below
    ``target_per_hour`` (false episodes are not monotone in the threshold: a higher one
    can split an episode in two, and the lowest scales join everything into one).

    Between the last level above the target and the next, ``log10 scale`` is interpolated
    linearly in the rate (as the matched FAR is). A log too short to hold one false episode
    at the target rate (``hours x target < 1``) cannot be matched.
    """
    match = BudgetMatch(target_per_hour)
    if not hours > 0:
        match.note = "no fault-free tested time outside the calibration window"
        return match
    if hours * target_per_hour < 1.0:
        match.note = (
            f"{hours:.3g} h of fault-free tested time is too short to match"
            f" {format_rate(target_per_hour)} (it holds {hours * target_per_hour:.2g} false"
            f" episodes at that rate; needs at least {1.0 / target_per_hour:.3g} h)"
        )
        return match
    rate = np.asarray(false_episodes, float) / hours
    above = np.flatnonzero(rate > target_per_hour)
    if above.size == 0:
        match.index, match.weight = 0, 1.0
        match.scale = float(10 ** BUDGET_LOG_SCALES[0])
        match.note = (
            f"at or below {format_rate(target_per_hour)} already at {match.scale:g} x the"
            " threshold (bottom of the range)"
        )
        return match
    last = int(above[-1])
    if last == rate.size - 1:
        match.note = (
            f"false episodes stay above {format_rate(target_per_hour)} up to"
            f" {10**BUDGET_LOG_HIGH:g} x the threshold"
        )
        return match
    index = last + 1
    drop = rate[last] - rate[index]
    weight = float((rate[last] - target_per_hour) / drop) if drop > 0 else 1.0
    low, high = BUDGET_LOG_SCALES[last], BUDGET_LOG_SCALES[index]
    match.index, match.weight = index, weight
    match.scale = float(10 ** (low + weight * (high - low)))
    return match


def read_budget(curve: BudgetCurve, match: BudgetMatch) -> dict[str, float | None]:
    """A curve's figures where ``match`` sits: MAR and FIR interpolated between the two
    levels at the match's weight, the delays at the upper (less sensitive) level; None
    where undefined or unmatched."""
    out: dict[str, float | None] = {name: None for name in BUDGET_FIGURES}
    if match.index is None:
        return out
    i, w = match.index, match.weight
    for name in BUDGET_FIGURES:
        values = curve.figures[name]
        hi = float(values[i])
        if name in ("mar", "fir") and i > 0 and w < 1.0 and not np.isnan(values[i - 1]):
            lo = float(values[i - 1])
            out[name] = None if np.isnan(hi) else lo + w * (hi - lo)
        else:
            out[name] = None if np.isnan(hi) else hi
    return out


def format_rate(per_hour: float) -> str:
    """``1/h``, ``0.1/h``, ``120/h``: a rate of episodes per hour as users write it."""
    return f"{per_hour:g}/h"


def poisson_upper(count: int, confidence: float = 0.95) -> float:
    """The exact one-sided upper confidence bound of a Poisson mean after ``count``
    events: the mean m with ``P(N <= count; m) = 1 - confidence``, i.e. the
    ``confidence`` quantile of Gamma(count + 1), ``chi2_confidence(2 count + 2) / 2``
    (Garwood 1936): 2.996 for 0 events at 95 %.

    Solved by Newton's method on the regularized incomplete gamma function (series and
    continued fraction, Numerical Recipes §6.2) from the Wilson-Hilferty start, to a
    relative 1e-13, without scipy (so that ``imufdi report`` does not import it).
    """
    a = count + 1.0
    if count == 0:
        return -math.log(1.0 - confidence)
    z = _normal_quantile(confidence)
    mean = a * (1.0 - 1.0 / (9.0 * a) + z / (3.0 * math.sqrt(a))) ** 3  # Wilson-Hilferty
    log_norm = math.lgamma(a)
    for _ in range(50):
        gap = _lower_gamma(a, mean) - confidence
        density = math.exp((a - 1.0) * math.log(mean) - mean - log_norm)
        step = gap / density
        mean = max(mean - step, 0.5 * mean)
        if abs(step) <= 1e-14 * mean:
            break
    return mean


def _lower_gamma(a: float, x: float) -> float:
    """The regularized lower incomplete gamma function P(a, x), a > 0, x >= 0."""
    if x <= 0.0:
        return 0.0
    log_front = a * math.log(x) - x - math.lgamma(a)
    if x < a + 1.0:  # the series
        term = total = 1.0 / a
        n = a
        while abs(term) > abs(total) * 1e-16:
            n += 1.0
            term *= x / n
            total += term
        return total * math.exp(log_front)
    # the continued fraction of Q(a, x) (modified Lentz)
    tiny = 1e-300
    b = x + 1.0 - a
    c, d = 1.0 / tiny, 1.0 / b
    h = d
    for i in range(1, 100_000):
        an = -i * (i - a)
        b += 2.0
        d = an * d + b
        d = tiny if abs(d) < tiny else d
        c = b + an / c
        c = tiny if abs(c) < tiny else c
        d = 1.0 / d
        delta = d * c
        h *= delta
        if abs(delta - 1.0) < 1e-16:
            break
    return 1.0 - math.exp(log_front) * h


def _normal_quantile(p: float) -> float:
    """The standard normal quantile (bisection on erfc: only a starting point)."""
    low, high = -10.0, 10.0
    for _ in range(80):
        mid = 0.5 * (low + high)
        if 0.5 * math.erfc(-mid / math.sqrt(2.0)) < p:
            low = mid
        else:
            high = mid
    return 0.5 * (low + high)
