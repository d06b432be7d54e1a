"""Alarm runs (:func:`~imufdi_cli.episodes.episode.find_episodes`)."""

from __future__ import annotations

import numpy as np

from imufdi_cli.episodes import find_episodes


def test_find_episodes_merges_short_gaps_only() -> None:
    alarm = np.array([0, 1, 1, 0, 1, 0, 0, 0, 1, 1, 0], dtype=bool)
    assert find_episodes(alarm, 0) == [(1, 3), (4, 5), (8, 10)]
    assert find_episodes(alarm, 1) == [(1, 5), (8, 10)]
    assert find_episodes(alarm, 3) == [(1, 10)]
    assert find_episodes(np.zeros(5, bool), 2) == []
    assert find_episodes(np.ones(3, bool), 0) == [(0, 3)]
