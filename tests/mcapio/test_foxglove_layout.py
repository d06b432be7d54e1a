"""The Foxglove layout shipped in docs/viewers/ opens a detected log: valid JSON, every
panel it names is laid out, and every topic and field path it names exists in the output
of ``imufdi detect -d glt`` (decoded by mcap-ros2-support, an independent reader)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from mcap_ros2.reader import read_ros2_messages

from tests.cli.conftest import invoke

LAYOUT = Path(__file__).resolve().parents[2] / "docs" / "viewers" / "foxglove-glt.json"
#: a message path: topic, then optional {field==value} filters and .field / [i] steps
PATH = re.compile(r"^(?P<topic>/[^.{\[]+)(?P<rest>.*)$")
FILTER = re.compile(r'^\{(?P<field>\w+)==(?P<value>"[^"]*"|[-\w.]+)\}')


def _paths(node: object) -> list[str]:
    """Every message path in a layout's panel configs (``value`` of plot and state
    transition series, ``topicPath`` of table and raw-message panels)."""
    found: list[str] = []
    if isinstance(node, dict):
        for key, value in node.items():
            if key in ("value", "topicPath") and isinstance(value, str):
                found.append(value)
            else:
                found.extend(_paths(value))
    elif isinstance(node, list):
        for item in node:
            found.extend(_paths(item))
    return found


def _panels(layout: object) -> list[str]:
    if isinstance(layout, str):
        return [layout]
    assert isinstance(layout, dict) and {"first", "second", "direction"} <= set(layout)
    return _panels(layout["first"]) + _panels(layout["second"])


@pytest.fixture(scope="module")
def detected(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("foxglove")
    log, faulty, out = d / "sim.mcap", d / "faulty.mcap", d / "detected.mcap"
    assert invoke(["simulate", "--imus", "4", "--duration", "6s", "-o", log]).code == 0
    fault = "step:imu0.gyro.x,at=3s,amp=2deg/s"
    assert invoke(["inject", log, "--fault", fault, "-o", faulty]).code == 0
    assert invoke(["detect", faulty, "-d", "glt", "--named-scores", "-o", out]).code == 0
    return out


def _follow(message: object, rest: str, path: str) -> None:
    """Walk ``.field`` and ``[i]`` steps of ``rest`` through a decoded message."""
    for step in re.findall(r"\.(\w+)|\[(\d+)\]", rest):
        field, index = step
        if field:
            assert hasattr(message, field), f"{path}: no field {field!r}"
            message = getattr(message, field)
        else:
            message = message[int(index)]  # type: ignore[index]


def test_layout_is_valid_json_with_every_panel_configured():
    layout = json.loads(LAYOUT.read_text(encoding="utf-8"))
    assert {"configById", "layout"} <= set(layout)
    panels = _panels(layout["layout"])
    assert sorted(panels) == sorted(layout["configById"])
    kinds = {p.split("!")[0] for p in panels}
    assert {"Plot", "StateTransitions", "Table"} <= kinds


def test_every_path_of_the_layout_exists_in_a_detected_log(detected):
    layout = json.loads(LAYOUT.read_text(encoding="utf-8"))
    paths = _paths(layout["configById"])
    assert any(p.endswith(".statistic") for p in paths)
    assert any(p.endswith(".threshold") for p in paths)
    assert any(p.endswith(".alarm") for p in paths)
    assert any("episode" in p for p in paths)
    by_topic: dict[str, list[object]] = {}
    for message in read_ros2_messages(str(detected)):
        by_topic.setdefault(message.channel.topic, []).append(message.ros_msg)
    for path in paths:
        match = PATH.match(path)
        assert match, path
        topic, rest = match["topic"], match["rest"]
        assert topic in by_topic, f"{path}: no topic {topic} in {sorted(by_topic)}"
        messages = by_topic[topic]
        while (flt := FILTER.match(rest)) is not None:
            field, value = flt["field"], flt["value"].strip('"')
            assert hasattr(messages[0], field), f"{path}: no field {field!r} to filter on"
            messages = [m for m in messages if str(getattr(m, field)) == value]
            assert messages, f"{path}: no message with {field} == {value!r}"
            rest = rest[flt.end() :]
        _follow(messages[0], rest, path)


def test_named_scores_are_written_only_when_asked(tmp_path, detected):
    out = tmp_path / "plain.mcap"
    assert invoke(["detect", detected, "-d", "glt", "-o", out]).code == 0
    topics = {m.channel.topic for m in read_ros2_messages(str(out))}
    assert "/imufdi/glt/gyro" in topics
    assert not any(t.endswith("/scores") for t in topics)


def test_score_field_names_are_ros_names():
    from imufdi_cli.errors import UsageError
    from imufdi_cli.mcapio.status import scores_fields

    assert scores_fields(["imu0.gyro.x", "IMU-1.accel.z", "3.gyro"]) == [
        "imu0_gyro_x",
        "imu_1_accel_z",
        "s_3_gyro",
    ]
    with pytest.raises(UsageError, match="distinct field names"):
        scores_fields(["a.b", "a_b"])
