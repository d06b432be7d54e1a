"""Matched-FAR threshold sweep on hand-made statistics with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from imufdi_cli.metrics import FaultWindow, compute_metrics
from imufdi_cli.sweep import EDGES, LOG_LOW, N_BINS, STEP, SweepAccumulator, ratio_bins

MS10 = 10_000_000


def test_ratio_bins_edges_and_undefined():
    stat = np.array([1.0, 1.0, 0.0, np.nan, 1.0, 2.0, 1e-9, np.inf])
    thr = np.array([1.0, np.inf, 1.0, 1.0, 0.0, 1.0, 1.0, 1.0])
    bins = ratio_bins(stat, thr)
    k1 = round(-LOG_LOW / STEP)  # edge of ratio 1
    assert bins[0] == k1 + 1  # r = 1 alarms at scale 1 (edge k1) but not above
    assert bins[1] == 0 and bins[2] == 0 and bins[3] == 0 and bins[4] == 0  # undefined
    assert bins[5] == int(np.floor(np.log10(2.0) / STEP)) + k1 + 1
    assert bins[6] == 0  # below the range: never alarms on the grid
    assert bins[7] == N_BINS + 1


def _case(n_free: int = 1000, n_faulty: int = 1000, seed: int = 0):
    rng = np.random.default_rng(seed)
    t = np.arange(n_free + n_faulty, dtype=np.int64) * MS10
    stat = np.concatenate([rng.exponential(1.0, n_free), rng.exponential(1.0, n_faulty) + 3.0])
    thr = np.full(t.size, 4.0)
    fault = FaultWindow("f", (0,), n_free * MS10)
    return t, stat, thr, fault


def test_curve_is_monotone_and_exact_at_the_edges():
    t, stat, thr, fault = _case()
    m = compute_metrics(
        t,
        stat > thr,
        np.zeros(t.size, int),
        n_sensors=2,
        faults=[fault],
        statistic=stat,
        threshold=thr,
        match_far=0.01,
    )
    acc = SweepAccumulator([fault.start_ns])
    free = t < fault.start_ns
    iso = np.where(free, 0, 1).astype(np.int8)
    acc.update(ratio_bins(stat, thr), t, free, iso, [~free])
    curve = acc.curve()
    assert np.all(np.diff(curve["far"]) <= 0) and np.all(np.diff(curve["mar"]) >= 0)
    assert curve["far"][0] == 1.0 and curve["mar"][-1] == 1.0
    for scale in (0.5, 1.0, 2.0):  # exact counts at the grid edges
        k = round((np.log10(scale) - LOG_LOW) / STEP)
        ratio = stat / thr
        assert curve["far"][k] == pytest.approx(np.mean(ratio[free] >= 10 ** EDGES[k]))
        assert curve["mar"][k] == pytest.approx(np.mean(ratio[~free] < 10 ** EDGES[k]))
    assert m.threshold_scale_at_far is not None and m.mar_at_far is not None


def test_matched_scale_interpolates_linearly_in_far():
    # fault-free ratios put FAR 0.04 at edge k and 0.00 at edge k + 1: target 0.01 lies
    # 3/4 of the way, so log10(scale) = EDGES[k] + 0.75 STEP and MAR moves 3/4 of its step
    k = round(-LOG_LOW / STEP)  # scale 1
    mid = lambda j: 10 ** (EDGES[j] + STEP / 2)  # noqa: E731  a ratio inside bin j + 1
    free_ratio = np.array([mid(k)] * 4 + [mid(k - 50)] * 96)  # 4 % just above scale 1
    faulty_ratio = np.array([mid(k)] * 10 + [mid(k + 100)] * 90)
    acc = SweepAccumulator([1000 * MS10])
    ratios = np.concatenate([free_ratio, faulty_ratio])
    bins = ratio_bins(ratios, np.ones(ratios.size))
    free = np.arange(ratios.size) < 100
    iso = np.where(free, 0, 1).astype(np.int8)
    acc.update(bins, np.arange(ratios.size, dtype=np.int64) * MS10, free, iso, [~free])
    match = acc.match(0.01)
    assert match.threshold_scale == pytest.approx(10 ** (EDGES[k] + 0.75 * STEP))
    assert match.far == pytest.approx(0.01)
    assert match.mar == pytest.approx(0.0 + 0.75 * 0.10)
    assert match.fir == pytest.approx(0.0)
    assert match.note is None


def test_delay_at_matched_far_uses_the_first_row_over_the_scale():
    t = np.arange(40, dtype=np.int64) * MS10
    stat = np.full(40, 0.5)
    stat[20:] = [0.8, 1.5, 3.0, 9.0] * 5  # fault from sample 20
    thr = np.ones(40)
    fault = FaultWindow("f", (0,), 20 * MS10)
    m = compute_metrics(
        t,
        stat > thr,
        np.zeros(40, int),
        n_sensors=1,
        faults=[fault],
        statistic=stat,
        threshold=thr,
        match_far=0.01,
        decided_ns=t + MS10,
    )
    # FAR is 0 for every scale above 0.5: the matched scale is just above 0.5 and the
    # first faulty row over it is sample 20, decided one sample later
    assert m.threshold_scale_at_far == pytest.approx(0.5, rel=0.03)
    assert m.detection_delay_at_far_s == pytest.approx(0.01)
    assert m.mar_at_far == pytest.approx(0.0)


def test_unsweepable_and_unreachable_targets_say_why():
    t = np.arange(20, dtype=np.int64) * MS10
    fault = FaultWindow("f", (0,), 10 * MS10)
    none = compute_metrics(
        t,
        np.zeros(20, bool),
        np.full(20, -1),
        n_sensors=1,
        faults=[fault],
        statistic=np.full(20, np.nan),
        threshold=np.full(20, np.inf),
        match_far=0.01,
    )
    assert none.mar_at_far is None and none.threshold_scale_at_far is None
    acc = SweepAccumulator([10 * MS10])
    assert "no sweepable statistic" in (acc.match(0.01).note or "")
    # every fault-free ratio infinite: FAR 1 at every scale
    bins = np.full(20, N_BINS + 1)
    free = np.arange(20) < 10
    acc.update(bins, t, free, np.where(free, 0, 1).astype(np.int8), [~free])
    match = acc.match(0.01)
    assert match.mar is None and "stays above" in (match.note or "")
