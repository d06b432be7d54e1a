"""The alarmed rows of one block of status rows, counted per alarm run at once (for
:class:`~imufdi_cli.episodes.builder.EpisodeBuilder`: what each group of alarms adds to
the run it belongs to, without a numpy call per group)."""

from __future__ import annotations

from itertools import pairwise
from typing import Any

import numpy as np


class BlockAlarms:
    """What the alarmed rows of one block add to the runs they belong to, found for the
    whole block at once: per group of alarms (merged across ``merge_gap``), the alarms,
    the rows that isolated a sensor and their count per sensor, the detector's finite
    amplitudes (sensor, value) and the largest finite statistic ratio.

    Parameters
    ----------
    groups : list of ndarray
        Row indices of the block's alarmed rows, one array per group, in order.
    isolated : ndarray, shape (A,), int
        Isolated sensor of each alarmed row (negative: none), A = all groups' rows.
    ratios : ndarray, shape (A,)
        Statistic / threshold of each alarmed row.
    amplitudes : ndarray, shape (N, n), optional
        The block's per-sensor amplitudes (NaN: none).
    sensors : int
        n.
    """

    def __init__(
        self,
        groups: list[np.ndarray],
        isolated: np.ndarray,
        ratios: np.ndarray,
        amplitudes: np.ndarray | None,
        sensors: int,
    ) -> None:
        self.sizes = [int(g.size) for g in groups]
        starts = np.cumsum([0, *self.sizes[:-1]])
        which = np.repeat(np.arange(len(groups)), self.sizes)  # each alarmed row's group
        nonnegative = isolated >= 0
        self.isolated_rows = np.bincount(which[nonnegative], minlength=len(groups)).tolist()
        valid = nonnegative & (isolated < sensors)
        self.counts = np.bincount(
            which[valid] * sensors + isolated[valid], minlength=len(groups) * sensors
        ).reshape(len(groups), sensors)
        finite = np.isfinite(ratios)
        self.has_peak = np.bincount(which[finite], minlength=len(groups)).tolist()
        peaks = np.maximum.reduceat(np.where(finite, ratios, -np.inf), starts)
        self.peaks = peaks.tolist()
        self.amplitudes: list[tuple[np.ndarray, np.ndarray]] | None = None
        if amplitudes is not None:
            alarmed = amplitudes[np.concatenate(groups)]
            rows, columns = np.nonzero(np.isfinite(alarmed))
            values = alarmed[rows, columns]
            bounds = np.searchsorted(rows, [*starts.tolist(), len(which)]).tolist()
            self.amplitudes = [(columns[a:b], values[a:b]) for a, b in pairwise(bounds)]

    def add(self, state: dict[str, Any], g: int) -> None:
        """Group ``g``'s alarms counted in the run ``state``."""
        state["quiet"] = 0
        state["alarms"] += self.sizes[g]
        state["isolated_rows"] += self.isolated_rows[g]
        if self.amplitudes is not None:
            state["amplitudes"].append(self.amplitudes[g])
        state["counts"] += self.counts[g]
        if self.has_peak[g]:
            state["peak"] = max(state["peak"], self.peaks[g])
