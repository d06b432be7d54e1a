"""The variance drop of a frozen output (:mod:`imufdi_cli.episodes.variance_drop`)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np

from imufdi_cli.episodes import EpisodeBuilder
from tests.episodes.helpers import RATE, SIGMA, status_rows


def test_variance_drop_monitor_false_alarm_probability_is_alpha() -> None:
    """One sensor of white noise tested against its own variance (calibration dof large):
    on non-overlapping windows (independent), the share below the threshold is alpha =
    5 %; 1000 windows give Binomial(1000, 0.05), 50 +- 6.9; 3.5 of those allowed. The
    result does not depend on the block size."""
    from imufdi_cli.episodes import VarianceDropMonitor

    window, windows = 100, 1000
    x = np.random.default_rng(26).normal(0, SIGMA, (window * windows + 1, 1))
    counts = []
    for block in (window * windows + 1, 333):
        monitor = VarianceDropMonitor(
            np.eye(1), np.array([SIGMA**2]), window=window, alpha=0.05, calibration_dof=1e9
        )
        rows = [monitor.update(x[i : i + block]) for i in range(0, x.shape[0], block)]
        alarm = np.concatenate([r.alarm for r in rows])
        assert alarm[:window].sum() == 0  # no test before W differences
        counts.append(int(alarm[window::window].sum()))
    assert counts[0] == counts[1]
    assert abs(counts[0] - 50) <= 3.5 * math.sqrt(1000 * 0.05 * 0.95)


def test_a_frozen_output_on_a_constant_rate_is_found_by_the_variance_drop() -> None:
    """Sixteen co-aligned triads on a constant rate; sensor 7 freezes at sample 1000 (its
    output stays truth + bias: no mean shift) and no detector alarms. The builder's
    variance-drop monitor raises one episode, isolates sensor 7, calls it stuck with its
    onset; before the freeze (10 s of 48 healthy sensors at alpha = 1e-7 per window) it
    raises none."""
    from imufdi_cli.episodes import VARIANCE_DROP, white_sigma

    rng = np.random.default_rng(27)
    n, length, freeze = 48, 1600, 1000
    H = np.tile(np.eye(3), (16, 1))
    truth = np.deg2rad([10.0, 10.0, 10.0]) @ H.T
    cal = truth + rng.normal(0, SIGMA, (200, n))
    m = truth + rng.normal(0, SIGMA, (length, n))
    m[freeze:, 7] = m[freeze - 1, 7]
    ids = [f"s{i}" for i in range(n)]
    template = EpisodeBuilder(
        "",
        "gyro",
        H,
        ids,
        np.full(n, SIGMA),
        RATE,
        calibration_samples=200,
        calibration_mean=cal.mean(axis=0),
        white_sigma=white_sigma(H, cal),
    )
    builder = template.for_detector("glt")
    assert template.for_detector("bank")._drop is None  # one builder per type runs it
    t_ns = np.arange(length, dtype=np.int64) * 10_000_000
    quiet = status_rows(np.zeros(length, bool), np.full(length, -1))
    episodes = []
    for start in range(0, length, 250):
        stop = min(start + 250, length)
        builder.feed(m[start:stop])
        block = SimpleNamespace(**{k: v[start:stop] for k, v in vars(quiet).items()})
        episodes += builder.rows(t_ns[start:stop], t_ns[start:stop], block)
    episodes += builder.finish()
    (episode,) = episodes
    assert episode.detector == VARIANCE_DROP and episode.sensors == ["s7"]
    assert episode.fault_class == "stuck"
    assert freeze * 10_000_000 < episode.start_ns <= (freeze + 100) * 10_000_000


def test_each_sensor_is_tested_against_the_quantile_of_its_own_calibration_dof() -> None:
    """Two sensors with the same windows of noise but different calibration dof: each
    alarms exactly when its ratio falls below its own F quantile (a smaller dof lowers the
    quantile), and one common dof gives the statistic -ln(min ratio) as before."""
    from imufdi_cli.episodes import VarianceDropMonitor, successive_difference_dof
    from imufdi_cli.episodes.numerics import _f_quantile

    window = 50
    rng = np.random.default_rng(35)
    x = rng.normal(0, SIGMA, (4000, 1)) * np.array([[1.0, 1.0]])
    x[:, 1] += rng.normal(0, 1e-12, 4000)  # the same ratios to 1e-9, not the same floats
    dofs = np.array([30.0, 300.0])
    monitor = VarianceDropMonitor(
        np.eye(2), np.full(2, SIGMA**2), window=window, alpha=0.1, calibration_dof=dofs
    )
    rows = monitor.update(x)
    quantiles = [_f_quantile(0.1, successive_difference_dof(window + 1), d) for d in dofs]
    assert quantiles[0] < quantiles[1]
    ratio = np.full((4000, 2), np.inf)
    half = 0.5 * np.diff(x, axis=0) ** 2
    sums = np.cumsum(half, axis=0)
    ratio[window:] = (sums[window - 1 :] - np.concatenate([[[0, 0]], sums[:-window]])) / (
        window * SIGMA**2
    )
    below = ratio < np.array(quantiles)
    decided = np.abs(ratio / np.array(quantiles) - 1) > 1e-6  # away from the cut
    assert np.all(rows.alarm[decided.all(axis=1)] == below.any(axis=1)[decided.all(axis=1)])
    only_second = below[:, 1] & ~below[:, 0] & decided.all(axis=1)
    assert only_second.any() and np.all(rows.isolated[only_second] == 1)
    common = VarianceDropMonitor(
        np.eye(2), np.full(2, SIGMA**2), window=window, alpha=0.1, calibration_dof=300.0
    ).update(x)
    assert np.all(common.threshold == -math.log(quantiles[1]))
    ready = np.isfinite(ratio[:, 0])
    assert np.allclose(common.statistic[ready], -np.log(ratio[ready].min(axis=1)), rtol=1e-9)
