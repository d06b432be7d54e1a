"""Matching episodes to injected faults and scoring them
(:mod:`imufdi_cli.episodes.scoring`)."""

from __future__ import annotations

import pytest

from imufdi_cli.episodes import match_episodes, score_episodes


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
