"""Matched-FAR threshold sweep on hand-made statistics with known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from imufdi_cli.metrics import FaultWindow, compute_metrics
from imufdi_cli.sweep import (
    BUDGET_FIGURES,
    BUDGET_LEVELS,
    BUDGET_LOG_SCALES,
    EDGES,
    LOG_LOW,
    N_BINS,
    STEP,
    AlarmEpisodes,
    BudgetCurve,
    SweepAccumulator,
    episode_gap_rows,
    match_budget,
    poisson_upper,
    ratio_bins,
    read_budget,
)

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


# --- alarm episodes and the matched budget -----------------------------------------------


def _builder_episode_starts(alarm, isolated, blocks, n):
    """Episode start rows of :class:`EpisodeBuilder` (explanations off) on the rows."""
    from imufdi_cli.detectors.base import DetectionBlock
    from imufdi_cli.episodes.builder import EpisodeBuilder

    H = np.random.default_rng(0).standard_normal((n, 3))
    builder = EpisodeBuilder("d", "gyro", H, [f"s{i}" for i in range(n)], np.ones(n), 100.0, explain=False)  # fmt: skip
    t = np.arange(alarm.size, dtype=np.int64) * MS10
    episodes, at = [], 0
    for k in blocks:
        rows = slice(at, at + k)
        at += k
        out = DetectionBlock(
            statistic=np.ones(k),
            threshold=np.ones(k),
            alarm=alarm[rows],
            isolated=isolated[rows],
            amplitude=np.full(k, np.nan),
            scores=np.zeros((k, n)),
        )
        builder.feed(np.zeros((k, n)))
        episodes += builder.rows(t[rows], t[rows], out)
    episodes += builder.finish()
    return sorted(int(e.start_ns // MS10) for e in episodes)


def _blocks(rng, total, largest):
    sizes = []
    while total > 0:
        sizes.append(int(min(total, rng.integers(1, largest))))
        total -= sizes[-1]
    return sizes


def test_alarm_episodes_are_the_episodes_the_builder_makes():
    # random alarm sequences (sparse, dense, bursts; rows isolating no sensor or one not
    # isolable), cut into different blocks on the two sides
    rng = np.random.default_rng(1)
    merge, join = episode_gap_rows(100.0, 0.1, 1.0)
    for _ in range(60):
        size, n = int(rng.integers(1, 2500)), int(rng.integers(3, 7))
        alarm = rng.random(size) < rng.choice([0.002, 0.02, 0.1, 0.5])
        for _ in range(int(rng.integers(0, 4))):
            start = int(rng.integers(0, size))
            alarm[start : start + int(rng.integers(1, 300))] = True
        isolated = np.where(rng.random(size) < 0.8, rng.integers(0, n, size), rng.choice([-1, -2], size))  # fmt: skip
        eligible = rng.random(size) < 0.7
        starts = _builder_episode_starts(alarm, isolated, _blocks(rng, size, 700), n)
        counter = AlarmEpisodes(1, n, merge, join)
        at = 0
        for k in _blocks(rng, size, 400):
            counter.update(alarm[at : at + k], isolated[at : at + k], eligible[at : at + k])
            at += k
        counter.finish()
        assert counter.episodes[0] == len(starts)
        assert counter.false_episodes[0] == sum(bool(eligible[s]) for s in starts)


def test_alarm_episodes_at_many_levels_are_each_level_alone():
    rng = np.random.default_rng(2)
    for _ in range(40):
        size, n, levels = int(rng.integers(1, 3000)), int(rng.integers(1, 6)), int(rng.integers(1, 10))  # fmt: skip
        bins = rng.exponential(3.0, size).astype(np.int64)
        edges = np.sort(rng.choice(20, levels, replace=False))
        isolated = rng.integers(-2, n, size)
        eligible = rng.random(size) < 0.6
        merge = int(rng.integers(0, 12))
        join = merge + int(rng.integers(0, 50))
        together = AlarmEpisodes(levels, n, merge, join)
        alone = [AlarmEpisodes(1, n, merge, join) for _ in range(levels)]
        at = 0
        for k in _blocks(rng, size, 600):
            alarm = bins[None, at : at + k] > edges[:, None]
            level, column = np.nonzero(alarm)
            together.update_sparse(level, column, isolated[at : at + k], eligible[at : at + k], k)
            for j, one in enumerate(alone):
                one.update(alarm[j], isolated[at : at + k], eligible[at : at + k])
            at += k
        for counter in (together, *alone):
            counter.finish()
        assert together.episodes.tolist() == [one.episodes[0] for one in alone]
        assert together.false_episodes.tolist() == [one.false_episodes[0] for one in alone]


def test_finished_counts_leave_the_stream_open():
    counter = AlarmEpisodes(1, 2, 2, 5)
    counter.update(np.array([True, True, False]), np.array([0, 0, -1]), np.ones(3, bool))
    assert counter.finished().episodes[0] == 1 and counter.episodes[0] == 0  # still open
    counter.update(np.array([True]), np.array([0]), np.ones(1, bool))  # the same run goes on
    counter.finish()
    assert counter.episodes[0] == 1


def test_poisson_upper_bound_is_the_chi_square_quantile(scipy_stats):
    for count in (0, 1, 5, 40, 1000):
        want = scipy_stats.chi2.ppf(0.95, 2 * count + 2) / 2
        # Newton on the incomplete gamma to 1e-13 against scipy's own root finding
        assert poisson_upper(count) == pytest.approx(want, rel=1e-10)
    assert poisson_upper(0) == pytest.approx(-np.log(0.05), rel=1e-12)


def test_budget_match_interpolates_in_the_rate_above_the_last_crossing():
    counts = np.zeros(BUDGET_LEVELS.size, np.int64)
    counts[:10] = 50  # low scales merge everything into few episodes: below the target
    counts[10:20] = 500
    counts[20] = 30
    counts[21:] = 0
    # 10 h: 3/h at level 20, 0 at 21; the target 1.5/h sits halfway in the rate
    match = match_budget(counts, 10.0, 1.5)
    assert match.index == 21 and match.weight == pytest.approx(0.5)
    log_scale = BUDGET_LOG_SCALES[20] + 0.5 * (BUDGET_LOG_SCALES[21] - BUDGET_LOG_SCALES[20])
    assert match.scale == pytest.approx(10**log_scale) and match.note is None
    curve = BudgetCurve(10.0, counts, {name: np.arange(counts.size, dtype=float) for name in BUDGET_FIGURES})  # fmt: skip
    read = read_budget(curve, match)
    assert read["mar"] == pytest.approx(20.5) and read["fir"] == pytest.approx(20.5)
    assert read["detection_delay_s"] == 21.0  # delays at the upper (less sensitive) level
    assert BudgetCurve.from_dict(curve.to_dict()).to_dict() == curve.to_dict()


def test_budget_match_says_when_it_cannot():
    counts = np.zeros(BUDGET_LEVELS.size, np.int64)
    short = match_budget(counts, 0.5, 1.0)
    assert short.scale is None and "too short" in (short.note or "") and "1 h" in short.note
    assert "no fault-free" in (match_budget(counts, 0.0, 1.0).note or "")
    bottom = match_budget(counts, 2.0, 1.0)
    assert bottom.index == 0 and "bottom of the range" in (bottom.note or "")
    counts[:] = 100
    top = match_budget(counts, 2.0, 1.0)
    assert top.scale is None and "stay above 1/h" in (top.note or "")
    assert read_budget(BudgetCurve.from_dict({"hours": 2.0}), top)["mar"] is None


def _best_by_hand(row: list[float]) -> int:
    finite = [(v, -j) for j, v in enumerate(row) if math.isfinite(v)]
    return -max(finite)[1] if finite else -1


def test_best_columns_is_the_first_largest_finite_score():
    # NaN, +inf and -inf never win; ties go to the first; no finite score: -1; any strides
    from imufdi_cli.sweep import best_columns

    rng = np.random.default_rng(4)
    for n in range(0, 6):
        scores = rng.normal(size=(300, n)).round(1)
        pick = rng.random((300, n))
        scores[pick < 0.2] = np.nan
        scores[(pick >= 0.2) & (pick < 0.3)] = np.inf
        scores[(pick >= 0.3) & (pick < 0.4)] = -np.inf
        want = [_best_by_hand(row) for row in scores.tolist()]
        assert best_columns(scores).tolist() == want
        wide = np.zeros((300, 2 * n + 1))
        wide[:, 1 : 2 * n + 1 : 2] = scores
        assert best_columns(wide[:, 1 : 2 * n + 1 : 2]).tolist() == want
        assert best_columns(scores).dtype == np.int64
