"""Per-row helpers of the metrics: ground truth per sample, alarm edges and runs, the
tested fault-free time, the isolation the sweeps judge; and the false-alarm budget's
figures from counts (rates with their bounds, the matched budget's figures)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from imufdi_cli.metrics.figures import FaultWindow, Metrics

NS_PER_S = 1_000_000_000


def faulty_matrix(t_ns: np.ndarray, windows: Sequence[FaultWindow], n_sensors: int) -> np.ndarray:
    """Ground truth per sample and sensor from fault windows.

    Returns
    -------
    ndarray, shape (N, n_sensors), bool
        ``[i, j]`` true when a window acting on sensor j holds ``start <= t_i < end``.
    """
    t_ns = np.asarray(t_ns, dtype=np.int64)
    faulty = np.zeros((t_ns.size, n_sensors), dtype=bool)
    for window in windows:
        active = t_ns >= window.start_ns
        if window.end_ns is not None:
            active &= t_ns < window.end_ns
        faulty[np.ix_(active, np.asarray(window.sensors, dtype=np.intp))] = True
    return faulty


def rising_edges(alarm: np.ndarray) -> np.ndarray:
    """Indices where ``alarm`` (N,) bool goes from False to True (index 0 if it starts True)."""
    alarm = np.asarray(alarm, dtype=bool)
    if alarm.size == 0:
        return np.zeros(0, dtype=np.intp)
    previous = np.concatenate([[False], alarm[:-1]])
    return np.flatnonzero(alarm & ~previous)


def persistent(alarm: np.ndarray, persist: int) -> np.ndarray:
    """True where the alarm is on for at least ``persist`` consecutive samples starting here."""
    alarm = np.asarray(alarm, dtype=bool)
    if persist <= 1 or alarm.size == 0:
        return alarm.copy()
    counts = np.convolve(alarm.astype(np.int64), np.ones(persist, dtype=np.int64), "full")
    # counts[i + persist - 1] = number of alarms in alarm[i : i + persist]
    window = counts[persist - 1 : persist - 1 + alarm.size]
    return window == persist


def judged_isolation(
    isolated: np.ndarray,
    scores: np.ndarray | None,
    n_sensors: int,
    best: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The sensor each row is judged isolated to at any threshold (the sweeps): its
    isolated sensor, or for a row the detector left unisolated (not ``-2``, not
    isolable) the sensor of its largest finite score (the first of equal ones).

    ``best``, when given, is that sensor per row, already found from the scores
    (:func:`imufdi_cli.sweep.best_columns`, -1 where none is finite); ``scores`` is then
    not read.

    Returns
    -------
    judged : ndarray, shape (k,), bool
    column : ndarray, shape (k,), int64
        The sensor where judged (0 elsewhere).
    """
    has_iso = isolated >= 0
    column = np.clip(np.where(has_iso, isolated, 0), 0, max(n_sensors - 1, 0))
    judged = has_iso.copy()
    if best is None and scores is not None and n_sensors:
        from imufdi_cli.sweep import best_columns

        k = int(isolated.size)
        best = best_columns(np.asarray(scores, dtype=np.float64).reshape(k, n_sensors))
    if best is not None and n_sensors:
        use = ~has_iso & (isolated != -2) & (best >= 0)
        column = np.where(use, best, column)
        judged |= use
    return judged, column


def budget_figures(curve: Any, match: Any) -> dict[str, float | None]:
    """The ``*_at_budget`` figures of a budget curve (one log's, or a campaign run's) read
    where ``match`` (perhaps pooled over runs) sits, by name."""
    from imufdi_cli.sweep import read_budget

    values = read_budget(curve, match)
    return {
        "target_budget_per_hour": match.target_per_hour,
        "threshold_scale_at_budget": match.scale,
        "mar_at_budget": values["mar"],
        "fir_at_budget": values["fir"],
        "detection_delay_s_at_budget": values["detection_delay_s"],
        "isolation_delay_s_at_budget": values["isolation_delay_s"],
    }


def apply_budget_match(metrics: Metrics, curve: Any, match: Any) -> None:
    """Set the ``*_at_budget`` figures of ``metrics`` (:func:`budget_figures`)."""
    for name, value in budget_figures(curve, match).items():
        setattr(metrics, name, value)


def episode_rate(count: int, hours: float) -> dict[str, float | None]:
    """False episodes per hour of ``hours`` fault-free tested time, with the exact Poisson
    95 % upper bound, and the mean time between them (hours) with its lower bound; all
    None without tested time (``mtbfa_h`` also without an episode)."""
    if not hours > 0:
        return dict.fromkeys(
            (
                "false_episodes_per_hour",
                "false_episodes_per_hour_upper95",
                "mtbfa_h",
                "mtbfa_h_lower95",
            )
        )
    from imufdi_cli.sweep import poisson_upper

    upper = poisson_upper(count) / hours
    return {
        "false_episodes_per_hour": count / hours,
        "false_episodes_per_hour_upper95": upper,
        "mtbfa_h": hours / count if count else None,
        "mtbfa_h_lower95": 1.0 / upper,
    }
