"""One explained alarm episode (:class:`Episode`), alarm runs, and the sensors an
episode isolates."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from imufdi_cli.episodes.fault_fit import FaultFit
from imufdi_cli.episodes.numerics import _finite, _median


def find_episodes(alarm: np.ndarray, merge_gap: int = 0) -> list[tuple[int, int]]:
    """Runs of alarms merged across gaps of at most ``merge_gap`` quiet samples.

    Parameters
    ----------
    alarm : array_like, shape (N,), bool
    merge_gap : int
        Longest run of quiet samples that does not end an episode.

    Returns
    -------
    list of (start, stop)
        Index ranges ``[start, stop)``; ``alarm[start]`` and ``alarm[stop - 1]`` are set.
    """
    alarm = np.asarray(alarm, dtype=bool)
    if merge_gap < 0:
        raise ValueError("merge_gap must be >= 0")
    padded = np.concatenate(([False], alarm, [False]))
    edges = np.flatnonzero(np.diff(padded.astype(np.int8)))
    starts, stops = edges[0::2], edges[1::2]
    if starts.size == 0:
        return []
    keep = np.concatenate(([True], starts[1:] - stops[:-1] > merge_gap))
    merged_starts = starts[keep]
    merged_stops = np.concatenate((stops[:-1][keep[1:]], stops[-1:]))
    return [(int(a), int(b)) for a, b in zip(merged_starts, merged_stops)]


#: :attr:`Episode.explained_by` of an episode explained by the profile-likelihood fits
FITS_EXPLANATION = "fits"
#: :attr:`Episode.explained_by` of a one-sample episode explained by its sample alone
SAMPLE_EXPLANATION = "sample"


@dataclass
class Episode:
    """One alarm episode of one detector on one sensor type, explained.

    Times are nanoseconds (log time of the samples); ``fits`` are best first.
    """

    detector: str
    sensor_type: str
    start_ns: int
    end_ns: int
    decided_start_ns: int
    decided_end_ns: int
    alarms: int
    sensors: list[str]
    peak_ratio: float
    runner_up: str | None = None
    runner_up_share: float | None = None
    fits: list[FaultFit] = field(default_factory=list)
    isolated_by: str = "detector"
    invalid_samples: int = 0
    fragments: int = 1
    #: the detector's own amplitude estimate of ``sensors[0]`` (median over the episode's
    #: alarms isolating it, from the status' per-sensor amplitudes), SI; None (and no
    #: ``amplitude`` key in :meth:`to_dict`) when none
    amplitude: float | None = None
    #: how ``fits`` were found: ``fits`` (every fault model by profile likelihood),
    #: ``sample`` (a one-sample episode of a per-sample test: the sample's residual
    #: against the consensus, :data:`SAMPLE_EXPLANATION`), None (not explained)
    explained_by: str | None = None

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) * 1e-9

    @property
    def fault_class(self) -> str | None:
        return self.fits[0].model if self.fits else None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (non-finite numbers become None)."""
        skip = {"fits"} | ({"amplitude"} if self.amplitude is None else set())
        out = _finite({k: v for k, v in vars(self).items() if k not in skip})
        out["duration_s"] = self.duration_s
        out["fault_class"] = self.fault_class
        out["fits"] = [f.to_dict() for f in self.fits]
        return out


def _sensor_amplitude(
    pairs: list[tuple[np.ndarray, np.ndarray]], sensor_ids: Sequence[str], names: list[str]
) -> float | None:
    """Median of the detector's amplitudes of the episode's sensor ``names[0]`` (``pairs``:
    (sensor index, amplitude) arrays of its alarms), or None."""
    if not names or not pairs:
        return None
    k = sensor_ids.index(names[0])
    if len(pairs) == 1:  # one alarm run
        values = pairs[0][1][pairs[0][0] == k]
    else:
        values = np.concatenate([v[c == k] for c, v in pairs])
    return _median(values) if values.size else None


def isolation_summary(
    isolated: np.ndarray, sensor_ids: Sequence[str]
) -> tuple[list[str], str | None, float | None]:
    """Sensors isolated during an episode, most often first, and the runner-up's share.

    Parameters
    ----------
    isolated : ndarray, shape (M,), int
        Isolated index per alarmed row (negative: none).
    """
    valid = isolated[isolated >= 0]
    if valid.size == 0:
        return [], None, None
    counts = np.bincount(valid, minlength=len(sensor_ids))
    order = [int(i) for i in np.argsort(-counts, kind="stable") if counts[i] > 0]
    names = [sensor_ids[i] for i in order]
    if len(order) < 2:
        return names, None, 0.0
    return names, names[1], float(counts[order[1]] / valid.size)
