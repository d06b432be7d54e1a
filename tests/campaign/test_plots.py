"""campaign.plots: legend labels, units on the amplitude axis, stable styles, the PNG."""

from __future__ import annotations

import math

import pytest

from imufdi_cli.campaign.plots import (
    _styles,
    detector_colour,
    detector_label,
    panel_axis,
    plot_curves,
    pretty_unit,
)
from imufdi_cli.colours import DETECTOR_COLOURS


def test_detector_label_has_no_json():
    assert detector_label("pca-parity", {"alpha": 0.001}) == "pca-parity α=0.001"
    assert detector_label("glt", {"window": 10}) == "glt window=10"
    assert detector_label("glt", {}) == "glt"
    assert detector_label("x", {"b": 2, "a": "z"}) == "x a=z b=2"  # sorted


def test_pretty_units():
    assert pretty_unit("deg/s") == "°/s"
    assert pretty_unit("deg/s^2") == "°/s²"
    assert pretty_unit("m/s^2") == "m/s²"


def point(amplitude, value, unit, si, mean=1.0):
    return {
        "amplitude": amplitude,
        "amplitude_value": value,
        "amplitude_unit": unit,
        "amplitude_si": si,
        "mean": mean,
        "std": 0.0,
        "n": 3,
    }


def test_panel_axis_keeps_the_spec_unit_and_converts_stragglers():
    deg = math.pi / 180.0
    curve = {
        "sensor_type": "gyro",
        "points": [
            point("0.3deg/s", 0.3, "deg/s", 0.3 * deg),
            point("0.9deg/s", 0.9, "deg/s", 0.9 * deg),
            point("0.01rad/s", 0.01, "rad/s", 0.01),  # one point written in SI
        ],
    }
    unit, xs = panel_axis([curve])
    assert unit == "deg/s"
    assert xs[0][:2] == [0.3, 0.9]
    assert xs[0][2] == pytest.approx(0.01 / deg)  # 0.573 deg/s, not 0.01
    unit, xs = panel_axis([{"sensor_type": "accel", "points": [point("2", 2.0, "", None)]}])
    assert unit == "" and xs[0] == [2.0]


def test_styles_are_keyed_by_detector_label_and_stable():
    curves = [
        {"detector": "glt", "params": {"window": 10}},
        {"detector": "pca-parity", "params": {"alpha": 0.001}},
        {"detector": "glt", "params": {}},
    ]
    styles = _styles(curves)
    assert list(styles) == ["glt", "glt window=10", "pca-parity α=0.001"]
    assert styles["glt"]["color"] == DETECTOR_COLOURS["glt"]  # defaults: the detector's colour
    assert styles["glt window=10"]["color"] != styles["glt"]["color"]  # a shade of it
    assert styles["pca-parity α=0.001"]["color"] == DETECTOR_COLOURS["pca-parity"]
    assert len({s["marker"] for s in styles.values()}) == 3
    # the same configuration gets the same style whatever the order of the curves
    assert _styles(list(reversed(curves))) == styles
    # unknown detectors get a colour from their name, the same every time
    assert detector_colour("my-detector") == detector_colour("my-detector")


@pytest.mark.draws  # run early, on one worker (tests/conftest.py)
def test_plot_curves_writes_a_png(tmp_path):
    pytest.importorskip("matplotlib")
    deg = math.pi / 180.0
    curves = []
    groups = []
    for det, params in (("glt", {}), ("pca-parity", {"alpha": 0.001})):
        points = [point(f"{a}deg/s", a, "deg/s", a * deg) for a in (0.3, 0.9)]
        curves.append(
            {
                "base": "paper-table4",
                "detector": det,
                "params": params,
                "fault": "step:imu0.gyro.x,at=12s",
                "model": "step",
                "sensor_type": "gyro",
                "unit": "deg/s",
                "points": points,
            }
        )
        for p in points:
            groups.append(
                {
                    "base": "paper-table4",
                    "detector": det,
                    "params": params,
                    "fault": "step:imu0.gyro.x,at=12s",
                    "model": "step",
                    "amplitude": p["amplitude"],
                    "mar": {"mean": 0.25, "std": 0.0, "n": 3},
                }
            )
    plot_curves({"name": "t", "groups": groups, "curves": curves}, tmp_path)
    data = (tmp_path / "detection_probability.png").read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
