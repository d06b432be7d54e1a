"""report --plot figures (imufdi_cli.plots): scale choice, which sensors are drawn, the
direction of isolation scores, stable colours, and a PNG that is written."""

from __future__ import annotations

import numpy as np
import pytest

from imufdi_cli import plots
from imufdi_cli.report import Report, ReportEntry


def entry(scores, isolated, alarm, faulty, name="pca-parity") -> ReportEntry:
    n = len(alarm)
    return ReportEntry(
        detector=name,
        sensor_type="gyro",
        sensor_ids=[f"imu{j}.gyro.x" for j in range(scores.shape[1])],
        metrics=None,  # type: ignore[arg-type]  # not drawn
        t_ns=np.arange(n, dtype=np.int64) * 10_000_000,
        statistic=np.linspace(1.0, 2.0, n),
        threshold=np.ones(n),
        alarm=np.asarray(alarm, bool),
        scores=scores,
        faulty=faulty,
        isolated=np.asarray(isolated, np.int64),
    )


def test_log_scale_when_statistic_and_threshold_differ_by_orders():
    assert plots.use_log_scale(np.array([900.0, 1100.0]), np.array([70.0, 70.0]))  # woa case
    assert not plots.use_log_scale(np.array([40.0, 140.0]), np.array([71.0]))  # glt case
    assert plots.use_log_scale(np.array([0.01, 5.0]), np.array([np.inf]))  # spans > 100
    assert not plots.use_log_scale(np.array([0.0, -1.0]), np.array([1.0]))  # nothing > 0


def test_smaller_is_worse_is_read_from_the_isolation_decisions():
    rng = np.random.default_rng(0)
    scores = rng.uniform(1.0, 1.5, size=(50, 6))
    scores[25:, 2] = 0.1  # pca-parity: the faulty sensor has the smallest angle
    alarm = np.arange(50) >= 25
    isolated = np.where(alarm, 2, -1)
    faulty = np.zeros((50, 6), bool)
    faulty[25:, 2] = True
    e = entry(scores, isolated, alarm, faulty)
    assert plots.smaller_is_worse(e)
    flipped = entry(-scores + 3.0, isolated, alarm, faulty, name="glt")  # largest = worst
    assert not plots.smaller_is_worse(flipped)


def test_suspects_are_the_faulty_then_the_wrongly_isolated():
    scores = np.zeros((10, 5))
    alarm = np.ones(10, bool)
    isolated = np.array([3] * 6 + [1] * 3 + [-1])
    faulty = np.zeros((10, 5), bool)
    faulty[:, 1] = True
    assert plots.suspects(entry(scores, isolated, alarm, faulty)) == [1, 3]
    none = np.zeros((10, 5), bool)
    assert plots.suspects(entry(scores, isolated, alarm, none)) == [3]  # the worst false one


@pytest.mark.draws  # run early, on one worker (tests/conftest.py)
def test_plot_report_writes_a_png(tmp_path):
    pytest.importorskip("matplotlib")
    rng = np.random.default_rng(1)
    scores = rng.uniform(1.0, 1.5, size=(200, 8))
    scores[100:, 4] = 0.2
    alarm = np.arange(200) >= 100
    faulty = np.zeros((200, 8), bool)
    faulty[100:, 4] = True
    e = entry(scores, np.where(alarm, 4, -1), alarm, faulty)
    report = Report(source="synthetic", has_truth=True, faults=[], entries=[e], notes=[], t0_ns=0)
    path = tmp_path / "r.png"
    plots.plot_report(report, str(path))
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_time_zero_is_the_log_start_detect_recorded():
    e = entry(np.zeros((3, 2)), [-1] * 3, [False] * 3, np.zeros((3, 2), bool))
    report = Report(source="s", has_truth=False, faults=[], entries=[e], notes=[], t0_ns=10**10)
    assert plots.origin_ns(report, e) == 10**10  # older logs: the first status sample
    report.records["pca-parity"] = {"t0_ns": 0}  # detect --start 10s: status from 10 s
    assert plots.origin_ns(report, e) == 0


def test_envelope_keeps_a_one_sample_spike_in_a_million():
    y = np.zeros(1_000_000)
    y[123_457] = 5.0
    y[876_543] = -3.0
    keep = plots.envelope(y, 1540)
    assert 123_457 in keep and 876_543 in keep  # both extremes drawn
    assert keep.size <= 3 * 1540 + 2 and np.all(np.diff(keep) > 0)
    assert keep[0] == 0 and keep[-1] == y.size - 1  # the line spans the same time


def test_envelope_keeps_min_and_max_of_every_column():
    rng = np.random.default_rng(2)
    n, columns = 100_003, 700  # not a multiple: a shorter last run
    y = rng.standard_normal(n)
    y[rng.random(n) < 0.01] = np.nan
    keep = plots.envelope(y, columns)
    per = -(-n // columns)
    for start in range(0, n, per):
        run = y[start : start + per]
        kept = keep[(keep >= start) & (keep < start + per)]
        assert np.nanmax(run) == np.nanmax(y[kept]) and np.nanmin(run) == np.nanmin(y[kept])
        assert np.isnan(run).any() == np.isnan(y[kept]).any()  # a gap stays a gap


def test_short_line_is_drawn_unchanged():
    y = np.arange(3000.0)
    np.testing.assert_array_equal(plots.envelope(y, 1540), np.arange(3000))
    assert plots.envelope(np.zeros(0), 10).size == 0


def test_row_quantiles_are_numpys_row_by_row():
    rng = np.random.default_rng(3)
    values = rng.chisquare(1, (200, 47))
    values[rng.random(values.shape) < 0.2] = np.nan  # rows of many different counts
    values[7] = np.nan  # no value: NaN
    low, mid, high = plots._row_quantiles(values)
    ok = ~np.isnan(values).all(axis=1)
    for got, want in (
        (low, np.nanpercentile(values[ok], 10, axis=1)),
        (mid, np.nanmedian(values[ok], axis=1)),
        (high, np.nanpercentile(values[ok], 90, axis=1)),
    ):
        np.testing.assert_array_equal(got[ok], want)  # the same numbers, bit for bit
        assert np.isnan(got[7])


def test_band_envelope_covers_the_band_of_every_column():
    rng = np.random.default_rng(4)
    t = np.arange(50_000) * 0.01
    low = rng.standard_normal(t.size)
    high = low + rng.uniform(0, 2, t.size)
    x, lo, hi = plots._band_envelope(t, low, high, 500)
    assert x.size == lo.size == hi.size <= 2 * 500
    assert lo.min() == low.min() and hi.max() == high.max()
    assert x[0] == t[0] and x[-1] == t[-1]
    short = plots._band_envelope(t[:900], low[:900], high[:900], 500)  # drawn unchanged
    for got, want in zip(short, (t[:900], low[:900], high[:900])):
        np.testing.assert_array_equal(got, want)


@pytest.mark.draws  # run early, on one worker (tests/conftest.py)
def test_long_report_figure_draws_the_envelope_and_the_same_shading():
    pytest.importorskip("matplotlib")
    n, k = 10_000, 6  # > 2 x 1540 pixel columns: drawn from the envelope
    rng = np.random.default_rng(5)
    scores = rng.uniform(1.0, 1.5, size=(n, k))
    faulty = np.zeros((n, k), bool)
    faulty[5_000:7_500, 4] = True
    scores[faulty] = 3.0
    alarm = faulty.any(axis=1)
    e = entry(scores, np.where(alarm, 4, -1), alarm, faulty)
    e.statistic = rng.chisquare(5, n)
    e.statistic[8_123] = 1e4  # one sample: on the figure
    report = Report(source="synthetic", has_truth=True, faults=[], entries=[e], notes=[], t0_ns=0)
    fig = plots.figure_report(report)
    try:
        stat_ax, iso_ax = fig.axes
        line = next(x for x in stat_ax.get_lines() if x.get_label().startswith("statistic"))
        assert line.get_xdata().size <= 3 * plots.ROW_WIDTH_IN * plots.DPI + 2
        assert np.max(line.get_ydata()) == 1e4
        assert stat_ax.get_yscale() == "log"
        # the shaded fault spans the first to the last faulty sample, as every sample would
        shade = stat_ax.collections[0].get_paths()[0].vertices[:, 0]
        t = e.t_ns / 1e9
        assert shade.min() == t[5_000] and shade.max() == t[7_499]
        faulty_line = next(x for x in iso_ax.get_lines() if "faulty" in str(x.get_label()))
        assert np.max(faulty_line.get_ydata()) == 3.0
    finally:
        plots.pyplot().close(fig)


@pytest.mark.draws  # run early, on one worker (tests/conftest.py)
def test_save_figure_writes_the_same_file_as_savefig(tmp_path):
    pytest.importorskip("matplotlib")
    plt = plots.pyplot()

    def figure():
        fig, ax = plt.subplots(figsize=(3, 2), constrained_layout=True)
        ax.plot([1, 2, 3], [10, 1000, 20], label="a line with a long label")
        ax.set_title("left\ntwo lines", loc="left")
        ax.set_ylabel("a\nwrapped label")
        ax.set_xticks([1, 3])  # few tick labels: the layout's cost is per text
        ax.set_yticks([10, 1000])
        fig.legend(loc="outside lower center")  # placed by the layout only
        return fig

    for name, save in (
        ("savefig", lambda fig, path: fig.savefig(path, dpi=60)),
        ("once", lambda fig, path: plots.save_figure(fig, path, 60)),
    ):
        fig = figure()
        try:
            save(fig, tmp_path / f"{name}.png")
        finally:
            plt.close(fig)
    assert (tmp_path / "once.png").read_bytes() == (tmp_path / "savefig.png").read_bytes()


def test_place_labels_never_overlap_nor_leave_the_panel():
    rng = np.random.default_rng(8)
    starts = rng.uniform(-0.1, 1.1, 60)
    widths = rng.uniform(0.05, 0.4, 60)
    spots = plots.place_labels(starts, widths, rows=2, gap=0.01)
    placed = [(x, row, w) for spot, w in zip(spots, widths) if spot for x, row in [spot]]
    assert placed and any(s is None for s in spots)  # 60 labels do not fit in 2 rows
    for x, _, w in placed:
        assert 0.0 <= x and x + w <= 1.0 + 1e-12
    anchors = {
        (x, row): min(max(a, 0.0), 1.0)
        for spot, a in zip(spots, starts)
        if spot
        for x, row in [spot]
    }
    for i, (x, row, w) in enumerate(placed):
        for y, other_row, v in placed[i + 1 :]:
            assert row != other_row or x + w + 0.01 <= y + 1e-12 or y + v + 0.01 <= x + 1e-12
        # no leader line (from a higher row down to the lane) crosses this label
        for (_, other_row), anchor in anchors.items():
            assert other_row <= row or not x <= anchor <= x + w
    # the first (most important) label always gets the first row, at its start when it fits
    assert spots[0] == (min(max(starts[0], 0.0), 1.0 - widths[0]), 0)
    assert plots.place_labels([0.2], [1.5], rows=2) == [None]  # wider than the panel


@pytest.mark.draws  # run early, on one worker (tests/conftest.py)
def test_report_figure_shades_calibration_and_labels_episodes_without_overprinting():
    pytest.importorskip("matplotlib")
    n, k = 4000, 6
    rng = np.random.default_rng(9)
    scores = rng.uniform(1.0, 1.5, size=(n, k))
    alarm = np.zeros(n, bool)
    episodes, spans = [], []
    for i, start in enumerate(range(300, 3900, 120)):  # 30 episodes, one every 1.2 s
        alarm[start : start + 40] = True
        ep = {
            "detector": "pca-parity",
            "sensor_type": "gyro",
            "start_ns": start * 10_000_000,
            "end_ns": (start + 39) * 10_000_000,
            "sensors": [f"imu{i % k}.gyro.x"],
            "fault_class": "step",
            "fits": [{"model": "step", "size": 0.01, "low": 0.009, "high": 0.011,
                      "size_name": "amp"}],
        }  # fmt: skip
        episodes.append(ep)
        spans.append((ep["start_ns"], ep["end_ns"]))
    e = entry(scores, np.where(alarm, 1, -1), alarm, np.zeros((n, k), bool))
    report = Report(
        source="synthetic", has_truth=False, faults=[], entries=[e], notes=[], t0_ns=0,
        episodes=episodes, episode_spans={("pca-parity", "gyro"): spans},
        records={"pca-parity": {"calibration_window_ns": [0, 2_000_000_000], "t0_ns": 0}},
    )  # fmt: skip
    fig = plots.figure_report(report)
    try:
        renderer = fig.canvas.get_renderer()
        fig.draw(renderer)
        stat_ax, iso_ax = fig.axes
        panel = stat_ax.get_window_extent(renderer)
        labels = [t for t in stat_ax.texts if ": step " in t.get_text()]
        assert 3 <= len(labels) < 30  # as many as fit, not all 30
        from matplotlib.text import Text

        boxes = [Text.get_window_extent(t, renderer) for t in labels]  # the text, not its leader
        for i, a in enumerate(boxes):
            assert panel.x0 <= a.x0 and a.x1 <= panel.x1 and panel.y0 <= a.y0 and a.y1 <= panel.y1
            for b in boxes[i + 1 :]:
                assert not a.overlaps(b), (a, b)
        legend = stat_ax.get_legend().get_window_extent(renderer)
        assert all(not legend.overlaps(b) for b in boxes)
        note = [t for t in stat_ax.texts if "episodes not labelled" in t.get_text()]
        assert note and note[0].get_text().startswith(f"{30 - len(labels)} of 30")
        # the data stay below the episode lane
        lane_px = min(b.y0 for b in boxes)
        line = next(x for x in stat_ax.get_lines() if x.get_label().startswith("statistic"))
        top = stat_ax.transData.transform((0, np.nanmax(line.get_ydata())))[1]
        assert top < lane_px
        # the calibration window, hatched on both panels
        for ax in (stat_ax, iso_ax):
            hatched = [p for p in ax.patches if p.get_hatch() == "///"]
            assert len(hatched) == 1
            # x extent in data units (axvspan draws a Rectangle from matplotlib 3.9, a Polygon
            # before: its path through its own transform is the span either way)
            span = hatched[0].get_path().transformed(hatched[0].get_patch_transform())
            assert (span.vertices[:, 0].min(), span.vertices[:, 0].max()) == (0.0, 2.0)
        assert any("calibration" in str(h.get_label()) for h in stat_ax.get_legend().legend_handles)
        # alarms as runs: 30 bars, not 1200 markers
        runs = [c for c in stat_ax.collections if len(c.get_paths()) == 30]
        assert runs
    finally:
        plots.pyplot().close(fig)
