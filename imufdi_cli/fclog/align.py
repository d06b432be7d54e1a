"""Array samples from asynchronous sensor streams (a flight controller's IMUs), streaming.

A flight controller samples each IMU on its own clock and logs accelerometer and gyro
readings as separate streams (PX4 ``sensor_accel``/``sensor_gyro``, ArduPilot
``ACC``/``GYR``) or together (PX4 ``vehicle_imu``, ArduPilot ``IMU``). The detectors need
array samples: every sensor at one instant. :class:`NearestAligner` builds them without
resampling, so every value written is a value the log holds:

- the grid is the stream with the fewest samples per second (no stream is upsampled);
- at each grid time ``g`` every stream contributes its sample nearest to ``g``, if it is
  within ``tolerance`` (half the grid period: a sample of a stream at the grid's rate
  always qualifies); a stream sample serves at most one array sample, the first grid
  time it is near (a later grid time wanting it gets none, so nothing is held or
  repeated, and the choice depends on the past only: reading in any pieces gives the
  same samples);
- a grid time where some stream has no sample within the tolerance is dropped (a gap);
- the array sample is stamped at the *latest* of its values' times: every value exists
  by then, so a decision on it has no look-ahead.

Memory: a stream's samples are kept until every grid time that could use them is
resolved; a stream silent for ``stall_s`` while the others go on no longer holds them
back (its missing stretch becomes a gap), so the buffers hold at most a few seconds.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np


@dataclass
class AlignCounts:
    """What the alignment kept and dropped.

    Attributes
    ----------
    samples : int
        Array samples produced.
    dropped : int
        Grid times without a sample of every stream within the tolerance.
    unused : list of int
        Per stream: samples that no array sample took (faster streams are subsampled;
        samples around gaps).
    late : list of int
        Per stream: samples older than the part of the grid already resolved (out of
        order in the file by more than ``stall_s``); dropped.
    max_skew_us : int
        Largest spread of the value times within one array sample.
    skew_sum_us : int
        Sum of the spreads (mean = skew_sum_us / samples).
    """

    samples: int = 0
    dropped: int = 0
    unused: list[int] = field(default_factory=list)
    late: list[int] = field(default_factory=list)
    max_skew_us: int = 0
    skew_sum_us: int = 0


_NEVER = np.iinfo(np.int64).min


def _first_claims(picks: np.ndarray, near: np.ndarray, last: int) -> tuple[np.ndarray, int]:
    """Which grid times may take their pick when a stream sample serves one array sample.

    ``picks`` (K,) non-decreasing absolute sample indices, ``near`` (K,) whether each is
    within the tolerance; the first grid time with a sample near keeps it (so the choice
    depends on the past only, and streaming in any pieces gives the same samples).
    ``last``: the sample the previous call's last near grid time took. Returns the claims
    (K,) and the new ``last``.
    """
    claim = near.copy()
    rows = np.flatnonzero(near)
    if rows.size == 0:
        return claim, last
    taken = picks[rows]
    previous = np.empty_like(taken)
    previous[0] = last
    previous[1:] = taken[:-1]
    claim[rows] = taken != previous
    return claim, int(taken[-1])


class NearestAligner:
    """Nearest-sample alignment of S streams onto the grid of stream ``reference``.

    Parameters
    ----------
    widths : sequence of int
        Values per sample of each stream (3 for one triad, 6 for gyro + accel).
    reference : int
        The grid stream (the one with the fewest samples per second).
    tolerance_us : int
        Largest distance between a grid time and a stream sample it takes.
    stall_s : float
        A stream with no sample for this long (in log time) while others have newer ones
        no longer holds back the resolution.
    """

    def __init__(
        self,
        widths: Sequence[int],
        reference: int,
        tolerance_us: int,
        *,
        stall_s: float = 2.0,
    ) -> None:
        self.widths = list(widths)
        self.reference = reference
        self.tolerance = int(tolerance_us)
        self.stall = int(stall_s * 1e6)
        n = len(self.widths)
        self._t = [np.zeros(0, np.int64) for _ in range(n)]
        self._v = [np.zeros((0, w)) for w in self.widths]
        self._used = [np.zeros(0, bool) for _ in range(n)]
        self._last_pick = [-1] * n  # absolute index of the last sample taken, per stream
        self._base = [0] * n  # absolute index of the buffer's first sample
        self._resolved = _NEVER  # grid times <= this are done
        self._newest = [_NEVER] * n
        self.counts = AlignCounts(unused=[0] * n, late=[0] * n)

    def add(self, stream: int, t_us: np.ndarray, values: np.ndarray) -> None:
        """Queue samples of one stream: times (K,) int64 µs and values (K, width)."""
        t_us = np.asarray(t_us, np.int64)
        if t_us.shape[0] == 0:
            return
        values = np.asarray(values, np.float64).reshape(t_us.shape[0], self.widths[stream])
        if self._resolved != _NEVER:
            # a sample no grid time still to come can take
            limit = self._resolved if stream == self.reference else self._resolved - self.tolerance
            late = t_us <= limit
            if late.any():
                self.counts.late[stream] += int(late.sum())
                t_us, values = t_us[~late], values[~late]
                if t_us.shape[0] == 0:
                    return
        t = np.concatenate([self._t[stream], t_us])
        v = np.concatenate([self._v[stream], values])
        used = np.concatenate([self._used[stream], np.zeros(t_us.shape[0], bool)])
        if t.shape[0] > 1 and bool(np.any(np.diff(t) < 0)):
            order = np.argsort(t, kind="stable")
            t, v, used = t[order], v[order], used[order]
        self._t[stream], self._v[stream], self._used[stream] = t, v, used
        self._newest[stream] = max(self._newest[stream], int(t[-1]))

    def _horizon(self, final: bool) -> int | None:
        """The latest grid time that no sample still to come can change (None: none)."""
        if final:
            return int(np.iinfo(np.int64).max)
        seen = [t for t in self._newest if t != _NEVER]
        if not seen:
            return None
        newest = max(seen)
        # a grid time is final once every stream that is not silent has a sample past its
        # tolerance window (a stream silent for the stall time holds nothing back)
        active = [t for t in seen if t > newest - self.stall]
        return min(active) - self.tolerance

    def pop(self, final: bool = False) -> tuple[np.ndarray, list[np.ndarray]]:
        """The array samples that can be decided now: stamps (K,) int64 µs (the latest
        value time of each) and per stream the values (K, width)."""
        horizon = self._horizon(final)
        grid = self._t[self.reference]
        count = 0 if horizon is None else int(np.searchsorted(grid, horizon, side="right"))
        if count == 0:
            if final:
                self._trim([np.zeros(0, np.int64)] * len(self.widths), np.zeros(0, bool), 0, True)
            return self._empty()
        g = grid[:count]
        keep = np.ones(count, bool)
        stamps = g.copy()
        low = g.copy()
        picks: list[np.ndarray] = []
        for s in range(len(self.widths)):
            t = self._t[s]
            if t.shape[0] == 0:
                keep[:] = False
                picks.append(np.zeros(count, np.int64))
                continue
            after = np.searchsorted(t, g, side="left")
            left = np.clip(after - 1, 0, t.shape[0] - 1)
            right = np.clip(after, 0, t.shape[0] - 1)
            nearest = np.where(np.abs(t[right] - g) < np.abs(g - t[left]), right, left)
            taken = t[nearest]
            near = np.abs(taken - g) <= self.tolerance
            claims, self._last_pick[s] = _first_claims(
                nearest + self._base[s], near, self._last_pick[s]
            )
            keep &= claims
            picks.append(nearest)
            stamps = np.maximum(stamps, np.where(near, taken, stamps))
            low = np.minimum(low, np.where(near, taken, low))
        values = [self._v[s][picks[s][keep]] for s in range(len(self.widths))]
        n_kept = int(keep.sum())
        self.counts.samples += n_kept
        self.counts.dropped += count - n_kept
        if n_kept:
            skew = (stamps - low)[keep]
            self.counts.max_skew_us = max(self.counts.max_skew_us, int(skew.max()))
            self.counts.skew_sum_us += int(skew.sum())
        self._resolved = int(g[-1])
        self._trim(picks, keep, count, final)
        return stamps[keep], values

    def _trim(self, picks: list[np.ndarray], keep: np.ndarray, count: int, final: bool) -> None:
        """Mark the samples used, drop what no later grid time can take, and count the
        samples dropped unused."""
        for s in range(len(self.widths)):
            t = self._t[s]
            if t.shape[0] == 0:
                continue
            self._used[s][picks[s][keep]] = True
            if final:
                cut = t.shape[0]
            elif s == self.reference:
                cut = count
            else:
                # the next grid time is after the resolved one: its window starts later
                cut = int(np.searchsorted(t, self._resolved - self.tolerance, side="right"))
            if cut:
                self.counts.unused[s] += int(cut - self._used[s][:cut].sum())
                self._t[s] = t[cut:]
                self._v[s] = self._v[s][cut:]
                self._used[s] = self._used[s][cut:]
                self._base[s] += cut

    def _empty(self) -> tuple[np.ndarray, list[np.ndarray]]:
        return np.zeros(0, np.int64), [np.zeros((0, w)) for w in self.widths]
