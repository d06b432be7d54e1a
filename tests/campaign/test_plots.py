"""campaign.plots: legend labels, units on the amplitude axis, stable styles, the PNG."""

from __future__ import annotations

import math

import pytest

from imufdi_cli.campaign.plots import (
    FIGURE,
    _styles,
    detector_colour,
    detector_label,
    figure_curves,
    headline_curves,
    headline_metrics,
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


def _groups(configs, amplitudes=(0.3, 0.9), budget=False):
    """Summary groups of a step on imu0.gyro.x: MAR falling with the amplitude."""
    groups = []
    for rank, (det, params) in enumerate(configs):
        for a in amplitudes:
            g = {
                "base": "paper-table4",
                "detector": det,
                "params": params,
                "fault": "step:imu0.gyro.x,at=12s",
                "model": "step",
                "amplitude": f"{a}deg/s",
                "sensor_type": "gyro",
                "mar": {"mean": 0.5, "std": 0.0, "n": 3},
                "mar_at_far": {"mean": 0.9 / (1 + a + rank), "std": 0.0, "n": 3},
                "detection_delay_at_far_s": {"mean": 0.1 / a, "std": 0.0, "n": 3},
                "target_far": 0.01,
            }
            if budget:
                g["mar_at_budget"] = {"mean": 0.8 / (1 + a + rank), "std": 0.0, "n": 3}
                g["detection_delay_s_at_budget"] = {"mean": 0.2 / a, "std": 0.0, "n": 3}
                g["target_budget_per_hour"] = 1.0
            groups.append(g)
    return groups


def test_headline_is_the_budget_when_the_summary_has_it_else_the_matched_far():
    configs = [("glt", {}), ("pca-parity", {"alpha": 0.001})]
    far = headline_metrics({"groups": _groups(configs)})
    assert (far.mar, far.delay, far.level) == (
        "mar_at_far",
        "detection_delay_at_far_s",
        "matched FAR 1 %",
    )
    budget = headline_metrics({"groups": _groups(configs, budget=True)})
    assert (budget.mar, budget.delay) == ("mar_at_budget", "detection_delay_s_at_budget")
    assert budget.level == "a budget of 1 false episodes/h"
    curves = headline_curves({"groups": _groups(configs, budget=True)}, budget.mar)
    [(key, panel)] = curves.items()
    assert key == ("paper-table4", "step:imu0.gyro.x,at=12s", "gyro")
    assert [p["mean"] for p in panel[0]["points"]] == [0.8 / 1.3, 0.8 / 1.9]


@pytest.mark.draws  # run early, on one worker (tests/conftest.py)
def test_the_legend_stays_inside_the_canvas_with_many_long_labels():
    pytest.importorskip("matplotlib")
    import matplotlib.pyplot as plt

    configs = [("glt", {}), ("glt", {"window": 10}), ("woa-mvmd-glt", {"population": 30})]
    configs += [("pca-parity", {"alpha": 0.001, "components": 4}), ("bank", {"mode": "gyro"})]
    configs += [("noise-glr", {"alpha": 0.001, "window": 50}), ("px4-selector", {})]
    configs += [("ap-consistency", {"reference": "others", "hold": 10})]
    fig = figure_curves({"name": "long", "groups": _groups(configs, (0.3, 0.6, 0.9, 1.5))})
    try:
        renderer = fig.canvas.get_renderer()
        fig.draw(renderer)  # the layout engine places the legend
        canvas = fig.get_window_extent(renderer)
        [legend] = fig.legends
        box = legend.get_window_extent(renderer)
        assert canvas.x0 <= box.x0 and box.x1 <= canvas.x1
        assert canvas.y0 <= box.y0 and box.y1 <= canvas.y1
        assert len(legend.get_texts()) == len(configs)
        titles = [ax.get_title() for ax in fig.axes if ax.get_visible()]
        assert any(t.endswith(": MAR") for t in titles)
        assert any(t.endswith(": detection delay") for t in titles)
        assert "at matched FAR 1 %" in fig._suptitle.get_text()
    finally:
        plt.close(fig)


@pytest.mark.draws  # run early, on one worker (tests/conftest.py)
def test_plot_curves_writes_a_png(tmp_path):
    pytest.importorskip("matplotlib")
    groups = _groups([("glt", {}), ("pca-parity", {"alpha": 0.001})])
    plot_curves({"name": "t", "groups": groups, "curves": []}, tmp_path)
    data = (tmp_path / FIGURE).read_bytes()
    assert FIGURE == "detection.png"
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
    # a summary without the headline metrics draws nothing (and writes no file)
    plot_curves({"name": "t", "groups": [], "curves": []}, tmp_path / "none")
    assert not (tmp_path / "none").exists()
