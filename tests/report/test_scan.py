"""The streaming scan's bounded plot series."""

from __future__ import annotations

import numpy as np

from imufdi_cli.report import scan


def test_plot_series_keep_every_alarm_when_decimating(monkeypatch):
    """The kept sample's alarm is the OR of the alarms since the previous kept sample,
    for any block sizes and after any number of halvings."""
    monkeypatch.setattr(scan, "PLOT_POINTS", 50)
    rng = np.random.default_rng(3)
    for _ in range(100):
        n = int(rng.integers(1, 2000))
        alarm = rng.random(n) < rng.choice([0.001, 0.01, 0.2])
        t = np.arange(n)
        series = scan._Series()
        pos = 0
        while pos < n:
            k = int(rng.integers(1, 300))
            series.add({"t_ns": t[pos : pos + k], "alarm": alarm[pos : pos + k]})
            pos += k
        kept = series.arrays()
        t_kept = kept["t_ns"]
        assert t_kept[0] == 0 and np.all(np.diff(t_kept) == series.stride)
        assert t_kept.size <= 2 * 50 + 300
        expected = [
            alarm[(t_kept[i - 1] + 1 if i else 0) : t_kept[i] + 1].any() for i in range(t_kept.size)
        ]
        assert kept["alarm"].tolist() == expected
        assert series.pending_alarm == bool(alarm[t_kept[-1] + 1 :].any())
