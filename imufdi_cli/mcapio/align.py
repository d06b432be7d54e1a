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
        Time slots not produced: too few topics had a sample (all of them must, unless
        the reader accepts partial samples: then fewer than half the IMUs).
    partial : int
        Samples produced with some topics missing (their values NaN; see
        :class:`_Aligner`'s ``quorum``).
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
    partial: int = 0
    late: dict[str, int] = field(default_factory=dict)
    messages: dict[str, int] = field(default_factory=dict)
    max_skew_ns: int = 0
    tolerance_ns: int = 0


#: A stream missing at least this many samples is reported (:meth:`_Aligner.missing_report`).
MISSING_REPORTED = 10


@dataclass
class _MissingRuns:
    """Where one stream had no sample, over the slots where some IMU had one."""

    count: int = 0
    first_ns: int | None = None
    last_ns: int | None = None
    run: int = 0  # the current run of consecutive missing slots
    longest: int = 0


class _Aligner:
    """Groups samples of S streams into time slots (stamps within ``tolerance``).

    Pending samples of all streams are kept together (stamps, stream index, values padded
    to a common width), so adding a chunk and resolving a block are a few numpy calls.

    ``quorum``: a slot is produced when at least this many of the first ``n_imus``
    streams (the IMUs; the others are magnetometers) have a sample in it; the values of
    the streams without one are NaN and :attr:`last_present` says which. None (the
    default): every stream must have a sample. Where each stream missed samples is
    tracked for :meth:`missing_report`.
    """

    def __init__(
        self,
        names: list[str],
        widths: list[int],
        tolerance: int,
        max_pending: int,
        *,
        quorum: int | None = None,
        n_imus: int | None = None,
    ) -> None:
        self.names = names
        self.quorum = quorum
        self.n_imus = len(names) if n_imus is None else n_imus
        #: After :meth:`resolve`: (K, S) bool, which streams had a sample in each slot it
        #: returned, when some did not (else None: all did).
        self.last_present: np.ndarray | None = None
        self.missing = [_MissingRuns() for _ in names]
        self.slots_seen = 0  # slots where some IMU had a sample
        self.first_slot_ns: int | None = None
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
        self.last_present = None
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
        present = counts >= 1
        complete = np.all(present, axis=1)
        missing = ~present
        for s, name in enumerate(self.names):
            self.stats.gaps[name] += int(missing[:, s].sum())
            self.stats.duplicates[name] += int(np.maximum(counts[:, s] - 1, 0).sum())
        imus_present = np.count_nonzero(present[:, : self.n_imus], axis=1)
        emit = complete if self.quorum is None else imus_present >= max(self.quorum, 1)
        self._note_missing(t_sorted[slot_start[:n_done]], missing, imus_present > 0)
        self.stats.dropped += int((~emit).sum())
        unique_keys, first = np.unique(key, return_index=True)
        first_slot = unique_keys // n_streams
        first_stream = unique_keys % n_streams
        keep = emit[first_slot]
        first, first_slot, first_stream = first[keep], first_slot[keep], first_stream[keep]
        rank = np.cumsum(emit) - 1
        k = int(emit.sum())
        partial = not bool(complete[emit].all())
        row = np.full((k, n_streams), -1 if partial else 0, np.int64)
        row[rank[first_slot], first_stream] = rows[first]
        if partial:
            have = row >= 0
            self.stats.partial += int(np.count_nonzero(~have.all(axis=1)))
            self.last_present = have
            row = np.maximum(row, 0)
            stamps = np.where(have, all_t[row], np.iinfo(np.int64).max)
            # a slot's stamp: the first IMU's (as for a complete slot), else its earliest
            slot_t = np.where(have[:, 0], stamps[:, 0], stamps.min(axis=1))
            latest = np.where(have, stamps, np.iinfo(np.int64).min).max(axis=1)
            skew = latest - stamps.min(axis=1)
            values = []
            for s in range(n_streams):
                part = all_v[row[:, s], : self.widths[s]]
                part[~have[:, s]] = np.nan
                values.append(part)
        else:
            stamps = all_t[row]
            slot_t = stamps[:, 0]
            skew = stamps.max(axis=1) - stamps.min(axis=1)
            values = [all_v[row[:, s], : self.widths[s]] for s in range(n_streams)]
        if k:
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
        return slot_t.copy(), values

    def _note_missing(self, slot_ns: np.ndarray, missing: np.ndarray, real: np.ndarray) -> None:
        """Track each stream's missing samples over the slots ``real`` (some IMU had a
        sample there): ``slot_ns`` (K,) stamps, ``missing`` (K, S)."""
        if not bool(real.any()):
            return
        slot_ns, missing = slot_ns[real], missing[real]
        if self.first_slot_ns is None:
            self.first_slot_ns = int(slot_ns[0])
        self.slots_seen += int(slot_ns.size)
        for s, track in enumerate(self.missing):
            gone = missing[:, s]
            if not bool(gone.any()):
                track.run = 0
                continue
            idx = np.flatnonzero(gone)
            track.count += int(idx.size)
            if track.first_ns is None:
                track.first_ns = int(slot_ns[idx[0]])
            track.last_ns = int(slot_ns[idx[-1]])
            # runs of consecutive missing slots; the first continues the carried run
            breaks = np.flatnonzero(np.diff(idx) > 1)
            starts = np.r_[idx[0], idx[breaks + 1]]
            ends = np.r_[idx[breaks], idx[-1]]
            lengths = ends - starts + 1
            if starts[0] == 0:
                lengths[0] += track.run
            track.longest = max(track.longest, int(lengths.max()))
            track.run = int(lengths[-1]) if ends[-1] == gone.size - 1 else 0

    def _note_complete(self, slot_ns: np.ndarray) -> None:
        """:meth:`_note_missing` for slots where every stream had a sample."""
        if slot_ns.size == 0:
            return
        if self.first_slot_ns is None:
            self.first_slot_ns = int(slot_ns[0])
        self.slots_seen += int(slot_ns.size)
        for track in self.missing:
            track.run = 0

    def missing_report(self, period_ns: float, *, produced: bool) -> list[str]:
        """One line per stream that missed at least :data:`MISSING_REPORTED` samples where
        some IMU had one: how many of those slots, between which times (s from the first
        slot), the longest run; ``produced``: the slots with it missing were produced
        (partial samples) rather than dropped. Fewer are incidental (a damaged chunk cuts
        a slot at each end) and only counted (:class:`AlignmentStats`)."""
        lines = []
        origin = self.first_slot_ns or 0
        for name, track in zip(self.names, self.missing):
            if track.count < MISSING_REPORTED or track.first_ns is None or track.last_ns is None:
                continue
            share = track.count / max(self.slots_seen, 1)
            lines.append(
                f"{name} has no sample in {track.count} of {self.slots_seen} array samples"
                f" ({share:.0%}) between {(track.first_ns - origin) * 1e-9:.6g} s and"
                f" {(track.last_ns - origin) * 1e-9:.6g} s from the log start (longest run"
                f" {track.longest * period_ns * 1e-9:.3g} s): the topic stopped or slowed; "
                + (
                    "the other IMUs are tested there (its values missing: detect replaces"
                    " them by the others' consensus)"
                    if produced
                    else "those array samples are dropped"
                )
            )
        return lines

    def _resolve_regular(
        self, all_t: np.ndarray, all_s: np.ndarray, all_v: np.ndarray, final: bool
    ) -> tuple[np.ndarray, list[np.ndarray]] | None:
        """:meth:`resolve` when the pending samples are regular: every time slot holds one
        sample of each stream, in stream order, with the same stamp, and slots are more
        than the tolerance apart (what an array logger writes). Then slot k is rows
        ``k * S .. k * S + S - 1`` and no sorting is needed; the result and the statistics
        are those of the general path. Before the end of the log the newest slot may be
        incomplete (a chunk of the file ends inside a slot): its first streams, in order,
        with one stamp. None when the samples are not regular."""
        n_streams = len(self.names)
        n = all_t.shape[0]
        k_all, tail = divmod(n, n_streams)
        if k_all == 0 or (tail and final):
            return None
        whole = k_all * n_streams
        if not bool((all_s[:whole].reshape(k_all, n_streams) == np.arange(n_streams)).all()):
            return None
        table = all_t[:whole].reshape(k_all, n_streams)
        stamps = table[:, 0]
        if not bool((table == stamps[:, None]).all()):
            return None
        if k_all > 1 and not bool((np.diff(stamps) > self.tolerance).all()):
            return None
        if tail:
            # the incomplete newest slot: streams 0 .. tail - 1 at one stamp, after the rest
            newest = all_t[whole:]
            if not (
                bool((all_s[whole:] == np.arange(tail)).all())
                and bool((newest == newest[0]).all())
                and int(newest[0]) - int(stamps[-1]) > self.tolerance
            ):
                return None
        # Not final: the newest complete slot may still gain samples (the general path's
        # horizon is its stamp: the streams after the incomplete slot's have none newer).
        k = k_all if final else k_all - 1
        if k == 0:
            return self.empty()
        boundary = int(stamps[k - 1])
        self.boundary = boundary if self.boundary is None else max(self.boundary, boundary)
        self.stats.n_aligned += k
        self._note_complete(stamps[:k])
        by_slot = all_v[:whole].reshape(k_all, n_streams, all_v.shape[1])
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
