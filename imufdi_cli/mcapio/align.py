"""Time alignment of the IMU topics of an array log into array samples (docs/formats.md)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# --- alignment --------------------------------------------------------------------------


@dataclass
class AlignmentStats:
    """What time alignment of the IMU topics found (nothing is filled in).

    Attributes
    ----------
    n_aligned : int
        Array samples produced (every topic had a sample at that time).
    gaps : dict
        Per topic: samples missing where other topics have one.
    duplicates : dict
        Per topic: extra samples in the same time slot (the first is kept).
    misaligned : int
        Aligned samples whose stamps matched only within the tolerance (not exactly).
    dropped : int
        Time slots not produced because at least one topic had no sample.
    late : dict
        Per topic: samples that arrived after their time slot was already produced
        (out of order by more than the other topics' lead); dropped.
    messages : dict
        Per topic: messages read.
    max_skew_ns : int
        Largest stamp spread within an aligned sample.
    tolerance_ns : int
        Stamps closer than this are the same time slot.
    """

    n_aligned: int = 0
    gaps: dict[str, int] = field(default_factory=dict)
    duplicates: dict[str, int] = field(default_factory=dict)
    misaligned: int = 0
    dropped: int = 0
    late: dict[str, int] = field(default_factory=dict)
    messages: dict[str, int] = field(default_factory=dict)
    max_skew_ns: int = 0
    tolerance_ns: int = 0


class _Aligner:
    """Groups samples of S streams into time slots (stamps within ``tolerance``).

    Pending samples of all streams are kept together (stamps, stream index, values padded
    to a common width), so adding a chunk and resolving a block are a few numpy calls.
    """

    def __init__(
        self, names: list[str], widths: list[int], tolerance: int, max_pending: int
    ) -> None:
        self.names = names
        self.widths = widths
        self.width = max(widths)
        self.tolerance = int(tolerance)
        self.max_pending = max_pending
        self.pending: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self.counts = np.zeros(len(names), np.int64)
        self.boundary: int | None = None  # stamps <= boundary are resolved
        #: After :meth:`resolve`: the (K, S, width) array whose [:, s, :widths[s]] are the
        #: values it returned, when they came from the regular path (else None).
        self.last_joint: np.ndarray | None = None
        self.stats = AlignmentStats(
            gaps=dict.fromkeys(names, 0),
            duplicates=dict.fromkeys(names, 0),
            late=dict.fromkeys(names, 0),
            messages=dict.fromkeys(names, 0),
            tolerance_ns=self.tolerance,
        )

    def empty(self) -> tuple[np.ndarray, list[np.ndarray]]:
        return np.zeros(0, np.int64), [np.zeros((0, w)) for w in self.widths]

    def min_pending(self) -> int:
        """Fewest samples waiting in any stream (or the most, if a stream is silent long)."""
        most = int(self.counts.max())
        return most if most > self.max_pending else int(self.counts.min())

    def _tally(self, target: dict[str, int], streams: np.ndarray) -> np.ndarray:
        counts = np.bincount(streams, minlength=len(self.names))
        for s in np.flatnonzero(counts).tolist():
            target[self.names[s]] += int(counts[s])
        return counts

    def add(self, streams: np.ndarray, t_ns: np.ndarray, values: np.ndarray) -> None:
        """Queue samples: stream index (n,), stamps (n,), values (n, <= width)."""
        streams = np.asarray(streams, np.int64)
        self._tally(self.stats.messages, streams)
        if self.boundary is not None:
            late = t_ns <= self.boundary
            if bool(late.any()):
                self._tally(self.stats.late, streams[late])
                keep = ~late
                streams, t_ns, values = streams[keep], t_ns[keep], values[keep]
        if t_ns.shape[0] == 0:
            return
        if values.shape[1] < self.width:
            values = np.pad(values, ((0, 0), (0, self.width - values.shape[1])))
        self.pending.append((t_ns, streams, values))
        self.counts += np.bincount(streams, minlength=len(self.names))

    def resolve(self, final: bool) -> tuple[np.ndarray, list[np.ndarray]]:
        """Stamps (K,) and per-stream values (K, width) of the time slots now complete."""
        self.last_joint = None
        if not self.pending:
            return self.empty()
        n_streams = len(self.names)
        if len(self.pending) == 1:
            all_t, all_s, all_v = self.pending[0]
        else:
            all_t = np.concatenate([p[0] for p in self.pending])
            all_s = np.concatenate([p[1] for p in self.pending])
            all_v = np.concatenate([p[2] for p in self.pending])
        regular = self._resolve_regular(all_t, all_s, all_v, final)
        if regular is not None:
            return regular
        present = self.counts > 0
        horizon: int | None = None
        if not final:
            if not bool(present.all()) and int(self.counts.max()) <= self.max_pending:
                return self.empty()
            # Newest stamp of each stream; a stream silent for long does not hold the rest.
            newest = np.full(n_streams, np.iinfo(np.int64).max)
            order_s = np.lexsort((all_t, all_s))
            last_of = np.flatnonzero(np.r_[all_s[order_s][1:] != all_s[order_s][:-1], True])
            newest[all_s[order_s][last_of]] = all_t[order_s][last_of]
            horizon = int(newest.min())
        order = np.argsort(all_t, kind="stable")
        t_sorted, s_sorted = all_t[order], all_s[order]
        new_slot = np.empty(t_sorted.shape[0], bool)
        new_slot[0] = True
        np.greater(np.diff(t_sorted), self.tolerance, out=new_slot[1:])
        slot = np.cumsum(new_slot) - 1
        slot_start = np.flatnonzero(new_slot)
        slot_end = t_sorted[np.r_[slot_start[1:] - 1, t_sorted.shape[0] - 1]]
        n_slots = slot_start.shape[0]
        if horizon is None:
            n_done = n_slots
        else:
            # A future sample (stamp >= horizon) cannot join a slot ending before this.
            n_done = int(np.searchsorted(slot_end + self.tolerance, horizon, side="left"))
        if n_done == 0:
            return self.empty()
        n_items = int(slot_start[n_done]) if n_done < n_slots else t_sorted.shape[0]
        slot, s_done, rows = slot[:n_items], s_sorted[:n_items], order[:n_items]
        boundary = int(slot_end[n_done - 1])
        self.boundary = boundary if self.boundary is None else max(self.boundary, boundary)
        key = slot * n_streams + s_done
        counts = np.bincount(key, minlength=n_done * n_streams).reshape(n_done, n_streams)
        complete = np.all(counts >= 1, axis=1)
        missing = counts == 0
        for s, name in enumerate(self.names):
            self.stats.gaps[name] += int(missing[:, s].sum())
            self.stats.duplicates[name] += int(np.maximum(counts[:, s] - 1, 0).sum())
        self.stats.dropped += int((~complete).sum())
        unique_keys, first = np.unique(key, return_index=True)
        first_slot = unique_keys // n_streams
        first_stream = unique_keys % n_streams
        keep = complete[first_slot]
        first, first_slot, first_stream = first[keep], first_slot[keep], first_stream[keep]
        rank = np.cumsum(complete) - 1
        k = int(complete.sum())
        row = np.zeros((k, n_streams), np.int64)
        row[rank[first_slot], first_stream] = rows[first]
        stamps = all_t[row]
        values = [all_v[row[:, s], : self.widths[s]] for s in range(n_streams)]
        if k:
            skew = stamps.max(axis=1) - stamps.min(axis=1)
            self.stats.misaligned += int(np.count_nonzero(skew))
            self.stats.max_skew_ns = max(self.stats.max_skew_ns, int(skew.max()))
        self.stats.n_aligned += k
        rest = order[n_items:]
        if rest.shape[0]:
            rest = np.sort(rest)  # keep arrival order
            self.pending = [(all_t[rest], all_s[rest], all_v[rest])]
            self.counts = np.bincount(all_s[rest], minlength=n_streams)
        else:
            self.pending = []
            self.counts = np.zeros(n_streams, np.int64)
        return stamps[:, 0].copy(), values

    def _resolve_regular(
        self, all_t: np.ndarray, all_s: np.ndarray, all_v: np.ndarray, final: bool
    ) -> tuple[np.ndarray, list[np.ndarray]] | None:
        """:meth:`resolve` when the pending samples are regular: every time slot holds one
        sample of each stream, in stream order, with the same stamp, and slots are more
        than the tolerance apart (what an array logger writes). Then slot k is rows
        ``k * S .. k * S + S - 1`` and no sorting is needed; the result and the statistics
        are those of the general path. None when the samples are not regular."""
        n_streams = len(self.names)
        n = all_t.shape[0]
        if n == 0 or n % n_streams:
            return None
        k_all = n // n_streams
        if not bool((all_s.reshape(k_all, n_streams) == np.arange(n_streams)).all()):
            return None
        table = all_t.reshape(k_all, n_streams)
        stamps = table[:, 0]
        if not bool((table == stamps[:, None]).all()):
            return None
        if k_all > 1 and not bool((np.diff(stamps) > self.tolerance).all()):
            return None
        # Not final: the newest slot may still gain samples (the general path's horizon).
        k = k_all if final else k_all - 1
        if k == 0:
            return self.empty()
        boundary = int(stamps[k - 1])
        self.boundary = boundary if self.boundary is None else max(self.boundary, boundary)
        self.stats.n_aligned += k
        by_slot = all_v.reshape(k_all, n_streams, all_v.shape[1])
        values = [by_slot[:k, s, : self.widths[s]] for s in range(n_streams)]
        self.last_joint = by_slot[:k]
        done = k * n_streams
        if done < n:
            self.pending = [(all_t[done:], all_s[done:], all_v[done:])]
            self.counts = np.bincount(all_s[done:], minlength=n_streams)
        else:
            self.pending = []
            self.counts = np.zeros(n_streams, np.int64)
        return stamps[:k].copy(), values
