"""Matching episodes to injected faults and scoring them
(:mod:`imufdi_cli.episodes.scoring`)."""

from __future__ import annotations

import numpy as np
import pytest

from imufdi_cli.episodes import TRUTH_SIZE_KEYS, match_episodes, score_episodes, truth_size
from imufdi_cli.episodes.scoring import EpisodeMatcher
from imufdi_cli.mcapio.events import match_fields


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


def _reference_match(episode: dict, faults: list[dict]) -> dict:
    """The definition of match_episodes written out plainly (as first written)."""
    sensors = episode.get("sensors") or []
    first = sensors[0] if sensors else None
    kind, hit = "false", None
    for fault in faults:
        end = fault.get("end_ns")
        overlaps = episode["end_ns"] >= fault["start_ns"] and (
            end is None or episode["start_ns"] < end
        )
        same_type = any(s.split(".")[1] == episode["sensor_type"] for s in fault["sensors"])
        if not overlaps or not same_type:
            continue
        if first in fault["sensors"]:
            kind, hit = "fault", fault
            break
        kind = "wrong_sensor"
    record: dict = {"match": kind, "fault_id": None if hit is None else hit["id"]}
    if hit is not None:
        best = (episode.get("fits") or [{}])[0]
        size = truth_size(hit)
        record["true_class"] = hit["model"]
        record["class_right"] = best.get("model") == hit["model"]
        record["true_size"] = size
        low, high = best.get("low"), best.get("high")
        record["covered"] = (
            None
            if size is None or not record["class_right"] or low is None or high is None
            else bool(low <= size <= high)
        )
    return record


def test_matcher_agrees_with_the_definition_on_random_episodes() -> None:
    """EpisodeMatcher (faults prepared once; what the report runs on the typed fields of
    each episode event) gives the records of the definition, key order included."""
    rng = np.random.default_rng(2)
    sensors = [f"imu{k}.{t}.{a}" for k in range(3) for t in ("gyro", "accel") for a in "xy"]
    models = ["step", "drift", "noise", "stuck", "spikes", "scale"]
    for _ in range(50):
        faults = []
        for j in range(int(rng.integers(0, 4))):
            start = int(rng.integers(0, 1000))
            model = str(rng.choice(models))
            faults.append(
                {
                    "id": f"f{j}",
                    "model": model,
                    "sensors": list(rng.choice(sensors, int(rng.integers(1, 3)), replace=False)),
                    "params": {} if model == "stuck" else {TRUTH_SIZE_KEYS[model]: 0.5},
                    "start_ns": start,
                    "end_ns": None if rng.random() < 0.3 else start + int(rng.integers(0, 500)),
                }
            )
        matcher = EpisodeMatcher(faults)
        for _ in range(40):
            start = int(rng.integers(0, 1500))
            sensor = str(rng.choice(sensors))
            fit = {
                "model": str(rng.choice(models)),
                "low": 0.4,
                "high": float(rng.choice([0.45, 0.6])),
            }
            episode = {
                "sensor_type": sensor.split(".")[1],
                "start_ns": start,
                "end_ns": start + int(rng.integers(0, 300)),
                "sensors": [] if rng.random() < 0.1 else [sensor],
                "fits": [] if rng.random() < 0.1 else [fit],
            }
            expected = _reference_match(episode, faults)
            got = matcher.match(*match_fields(episode))
            assert list(got.items()) == list(expected.items())
            assert match_episodes([episode], faults) == [expected]
