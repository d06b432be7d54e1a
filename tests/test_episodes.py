"""Alarm episodes: extraction, leave-one-out residuals, fault-model fits and intervals."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
from numpy.testing import assert_allclose

from imufdi_cli.episodes import (
    EpisodeBuilder,
    find_episodes,
    fit_models,
    leave_one_out,
    match_episodes,
    score_episodes,
)

RATE = 100.0
SIGMA = np.deg2rad(0.15)


def test_find_episodes_merges_short_gaps_only() -> None:
    alarm = np.array([0, 1, 1, 0, 1, 0, 0, 0, 1, 1, 0], dtype=bool)
    assert find_episodes(alarm, 0) == [(1, 3), (4, 5), (8, 10)]
    assert find_episodes(alarm, 1) == [(1, 5), (8, 10)]
    assert find_episodes(alarm, 3) == [(1, 10)]
    assert find_episodes(np.zeros(5, bool), 2) == []
    assert find_episodes(np.ones(3, bool), 0) == [(0, 3)]


def test_leave_one_out_on_a_co_aligned_array_is_the_mean_of_the_others() -> None:
    n = 6
    H = np.tile(np.eye(3), (2, 1))
    rng = np.random.default_rng(0)
    m = rng.normal(size=(50, n))
    residual, prediction, consensus = leave_one_out(H, m, 0.2, 1)
    # sensor 1 is the y axis of the first triad; the only other y sensor is sensor 4
    assert_allclose(prediction, m[:, 4])
    assert_allclose(residual, m[:, 1] - m[:, 4])
    assert consensus == pytest.approx(0.2)
    H16 = np.tile(np.eye(3), (16, 1))
    _, _, consensus16 = leave_one_out(H16, rng.normal(size=(5, 48)), 0.3, 0)
    assert consensus16 == pytest.approx(0.3 / math.sqrt(15))


def _trace(model: str, size: float, rng: np.random.Generator, length: int = 400, onset: int = 150):
    t = np.arange(length) / RATE
    truth = np.deg2rad(10) + np.deg2rad(5) * np.sin(2 * np.pi * 0.5 * t)
    consensus_sigma = SIGMA / math.sqrt(15)
    y = truth + rng.normal(0, SIGMA, length)
    if model == "step":
        y[onset:] += size
    elif model == "drift":
        y[onset:] += size * (t[onset:] - t[onset])
    elif model == "noise":
        y[onset:] += rng.normal(0, SIGMA * math.sqrt(size**2 - 1), length - onset)
    elif model == "scale":
        y[onset:] = truth[onset:] * size + (y[onset:] - truth[onset:])
    elif model == "spikes":
        events = rng.random(length - onset) < 0.05
        y[onset:] += events * size * rng.choice([-1.0, 1.0], length - onset)
    elif model == "stuck":
        y[onset:] = y[onset - 1]
    prediction = truth + rng.normal(0, consensus_sigma, length)
    return y - prediction, prediction, t, consensus_sigma


CASES = [
    ("step", np.deg2rad(0.9)),
    ("drift", np.deg2rad(10)),
    ("noise", 3.0),
    ("scale", 1.5),
    ("spikes", np.deg2rad(3)),
]


@pytest.mark.parametrize(("model", "size"), CASES)
def test_fits_classify_and_their_90_percent_intervals_cover(model: str, size: float) -> None:
    """Monte Carlo under the model's own assumptions (white Gaussian noise, known sigma):
    the class is right and the 90 % interval covers the truth 90 % of the time. With 200
    trials the coverage has a binomial standard deviation of 2.1 points; the test allows
    3.5 of them either side (a false failure once in ~2000 runs)."""
    rng = np.random.default_rng(20261122)
    trials, right, covered = 200, 0, 0
    for _ in range(trials):
        r, o, t, c = _trace(model, size, rng)
        best = fit_models(r, o, t, SIGMA, c, onset_range=(50, 250))[0]
        right += best.model == model
        covered += best.model == model and best.low <= size <= best.high
    assert right / trials >= 0.97
    half = 3.5 * math.sqrt(0.9 * 0.1 / trials)
    assert 0.9 - half <= covered / right <= 0.9 + half


def test_a_frozen_output_is_stuck_with_its_value_and_onset() -> None:
    rng = np.random.default_rng(3)
    r, o, t, c = _trace("stuck", 0.0, rng)
    y = r + o
    y[150:] = y[149]  # the sensor's own output, frozen exactly
    best = fit_models(r, o, t, SIGMA, c, onset_range=(50, 250), raw=y)[0]
    assert best.model == "stuck"
    assert best.onset_index == 150
    assert best.size == y[149]


def test_step_onset_is_found_to_the_sample() -> None:
    rng = np.random.default_rng(4)
    r, o, t, c = _trace("step", np.deg2rad(2.0), rng)
    best = fit_models(r, o, t, SIGMA, c, onset_range=(50, 250))[0]
    assert (best.model, best.onset_index) == ("step", 150)


def _status(alarm: np.ndarray, isolated: np.ndarray) -> SimpleNamespace:
    n = alarm.size
    return SimpleNamespace(
        alarm=alarm, isolated=isolated, statistic=np.where(alarm, 3.0, 0.5), threshold=np.ones(n)
    )


def test_builder_gives_the_same_episodes_whatever_the_block_size() -> None:
    rng = np.random.default_rng(7)
    n_sensors, length = 12, 1500
    H = np.tile(np.eye(3), (4, 1))
    m = rng.normal(0, SIGMA, (length, n_sensors))
    m[600:900, 5] += np.deg2rad(1.0)
    alarm = np.zeros(length, bool)
    alarm[605:900:2] = True  # flickering inside the fault: one episode with merge_gap >= 1
    alarm[1200] = True  # a lone false alarm
    isolated = np.where(alarm, 5, -1).astype(np.int32)
    isolated[1200] = 2
    t_ns = np.arange(length, dtype=np.int64) * 10_000_000
    results = []
    for block in (7, 64, 1500):
        builder = EpisodeBuilder("glt", "gyro", H, [f"s{i}" for i in range(12)], SIGMA, RATE)
        episodes = []
        for start in range(0, length, block):
            stop = min(start + block, length)
            builder.feed(m[start:stop])
            status = _status(alarm[start:stop], isolated[start:stop])
            episodes += builder.rows(t_ns[start:stop], t_ns[start:stop] + 5, status)
        episodes += builder.finish()
        results.append([e.to_dict() for e in episodes])
    assert results[0] == results[1] == results[2]
    fault, lone = results[0]
    assert (fault["start_ns"], fault["end_ns"]) == (605 * 10_000_000, 899 * 10_000_000)
    assert fault["decided_start_ns"] == 605 * 10_000_000 + 5
    assert fault["sensors"] == ["s5"] and fault["fault_class"] == "step"
    step = fault["fits"][0]
    assert step["low"] <= np.deg2rad(1.0) <= step["high"]
    assert lone["sensors"] == ["s2"] and lone["alarms"] == 1


def test_builder_memory_is_bounded_by_margin_and_window() -> None:
    H = np.tile(np.eye(3), (4, 1))
    builder = EpisodeBuilder(
        "glt", "gyro", H, [f"s{i}" for i in range(12)], SIGMA, RATE, max_window_s=1.0
    )
    rng = np.random.default_rng(8)
    for start in range(0, 20_000, 500):
        block = rng.normal(0, SIGMA, (500, 12))
        builder.feed(block)
        status = _status(np.ones(500, bool), np.full(500, 3, np.int32))
        assert builder.rows(np.arange(start, start + 500) * 10_000_000, np.zeros(500), status) == []
        state = builder._open
        assert state is not None and state["kept"] <= builder.margin + builder.max_window
    (episode,) = builder.finish()
    assert episode.alarms == 20_000


def _episode(start: int, end: int, sensor: str, model: str, low: float, high: float) -> dict:
    return {
        "sensor_type": sensor.split(".")[1],
        "start_ns": start,
        "end_ns": end,
        "sensors": [sensor],
        "fits": [{"model": model, "low": low, "high": high}],
        "fault_class": model,
    }


def test_episodes_are_matched_to_the_fault_they_explain_and_scored() -> None:
    faults = [
        {
            "id": "f0",
            "model": "step",
            "sensors": ["imu3.gyro.x"],
            "params": {"amp": 0.5},
            "start_ns": 100,
            "end_ns": 400,
        },
        {
            "id": "f1",
            "model": "stuck",
            "sensors": ["imu1.gyro.y"],
            "params": {},
            "start_ns": 500,
            "end_ns": 600,
        },
    ]
    episodes = [
        _episode(120, 300, "imu3.gyro.x", "step", 0.4, 0.6),  # right, covered
        _episode(320, 330, "imu3.gyro.x", "step", 0.6, 0.7),  # right, not covered
        _episode(50, 60, "imu5.gyro.x", "none", 0, 0),  # before any fault: false
        _episode(150, 160, "imu7.gyro.z", "spikes", 0, 1),  # during f0, other sensor
        _episode(550, 700, "imu1.gyro.y", "noise", 1, 2),  # f1, wrong class
        _episode(700, 710, "imu1.gyro.y", "step", 0, 1),  # after f1 ended: false
        _episode(150, 160, "imu3.accel.x", "step", 0, 1),  # other sensor type: false
    ]
    matches = match_episodes(episodes, faults)
    assert [m["match"] for m in matches] == [
        "fault",
        "fault",
        "false",
        "wrong_sensor",
        "fault",
        "false",
        "false",
    ]
    assert matches[0]["covered"] is True and matches[1]["covered"] is False
    assert matches[4]["class_right"] is False and matches[4]["covered"] is None
    score = score_episodes(matches, hours=0.5)
    assert score["episodes"] == 7 and score["matched"] == 3 and score["false"] == 3
    assert score["false_episodes_per_hour"] == pytest.approx(6.0)
    assert score["class_accuracy"] == pytest.approx(2 / 3)
    assert score["coverage"] == pytest.approx(0.5)
    assert score["per_model"]["stuck"]["class_accuracy"] == 0.0
    assert score["per_model"]["step"]["coverage"] == pytest.approx(0.5)
