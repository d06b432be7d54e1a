"""Figures of ``imufdi report --plot`` (needs the ``plot`` extra: matplotlib).

:func:`plot_report` draws, per detector and sensor type, the detection statistic against
its threshold with the alarms marked as runs (like Li et al. Figure 15) and the isolation
scores of the suspect sensors against the spread of all the others; :func:`plot_roc` the
threshold sweep. As the papers draw them: the calibration window is shaded (hatched: in
sample, never scored), the injected faults are shaded, the explained episodes are bars in
a lane of their own with labels placed so that none overlaps another or leaves the panel
(:func:`place_labels`; the ones that do not fit are counted, not overprinted). Colours are
stable per detector (:func:`detector_colour`), so the same detector has the same colour in
every figure. Lines of more samples than twice the figure's width in pixels are drawn
from their min/max envelope (:func:`envelope`: every spike stays), with the median of
each pixel bin on top; the suspect sensors' scores as the median of each bin of
:data:`ISOLATION_BINS` with its 10–90 % band, so that a long log is not a solid band.
Figures are saved with their layout computed once (:func:`save_figure`).
"""

from __future__ import annotations

import textwrap
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from imufdi_cli.colours import detector_colour
from imufdi_cli.errors import UsageError
from imufdi_cli.report import Report, ReportEntry, format_size

#: colours of the isolated (not truly faulty) suspect sensors: none red, none alike
SUSPECT_COLOURS = ("#9467bd", "#17becf", "#8c564b", "#e377c2")
ALARM_COLOUR = "#d62728"
FAULT_COLOUR = "#d62728"
#: the statistic is drawn on a log axis when its positive values span more than
#: LOG_SPREAD (max / min) or its peak exceeds the median threshold LOG_OVER_THRESHOLD
#: times: then a threshold of 70 is not squashed under values near 1000
LOG_SPREAD = 100.0
LOG_OVER_THRESHOLD = 10.0
#: suspect sensors drawn one by one in the isolation panel (the rest as a band)
SUSPECTS = 3
#: rows of episode labels per panel (labels that fit in none are counted, not drawn)
EPISODE_LABEL_ROWS = 2
#: the alarm lane of a statistic panel, in axes fraction (bottom, top); the episode
#: lane (bars, :data:`EPISODE_LANE_HEIGHT` high) and its label rows go above the data,
#: under the legend (placed once the panel is laid out, :func:`_mark_episodes`)
ALARM_LANE = (0.0, 0.03)
EPISODE_LANE_HEIGHT = 0.035
#: share of the data span added on top of a statistic panel for the lanes and the legend
#: (raised when the legend and labels need more)
STATISTIC_HEADROOM = 0.9
#: bins (median and 10-90 % band) of the suspect sensors' scores in the isolation panel
ISOLATION_BINS = 300
CALIBRATION_COLOUR = "0.55"
#: resolution of the report figure, dots per inch
DPI = 110
#: width of one row of the report figure, inches (two panels side by side)
ROW_WIDTH_IN = 14.0


def pyplot() -> Any:
    """matplotlib.pyplot on the Agg backend; UsageError (exit 2) with the install hint when
    matplotlib is missing (``report --plot`` checks this before any work)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as err:
        raise UsageError(
            "--plot needs matplotlib, which is not installed: pip install 'imufdi-cli[plot]'"
            " (or drop --plot)"
        ) from err
    return plt


def save_figure(fig: Any, path: Any, dpi: float) -> None:
    """``fig.savefig(path, dpi=dpi)`` with its constrained layout computed once.

    ``savefig`` of a figure with a layout engine first draws the whole figure without
    rendering, only to run the layout, then draws it again; here the layout runs alone
    (``LayoutEngine.execute``, at ``dpi``) and the figure is drawn once. The file is the
    same, byte for byte (tests/test_plots.py); the draw it saves is about 0.1 s of CPU
    per report row.
    """
    import matplotlib

    fig.set_dpi(dpi)
    engine = fig.get_layout_engine()
    if engine is not None:
        engine.execute(fig)
        # set_layout_engine(None) falls back on these rcParams: keep no engine at all
        with matplotlib.rc_context(
            {"figure.autolayout": False, "figure.constrained_layout.use": False}
        ):
            fig.set_layout_engine(None)
    fig.savefig(path, dpi=dpi)


def _headroom(ax: Any, share: float = 0.5) -> None:
    """Extend the axis' top (the visual top, also when inverted) by ``share`` of its span,
    so that the legend sits above the data instead of over it."""
    bottom, top = ax.get_ylim()
    if ax.get_yscale() == "log" and bottom > 0 and top > 0:
        ax.set_ylim(bottom, top * (top / bottom) ** share)
    else:
        ax.set_ylim(bottom, top + share * (top - bottom))


def _wrap(text: str, width: int = 42) -> str:
    return "\n".join(textwrap.wrap(text, width)) if len(text) > width else text


def _described(report: Report, entry: ReportEntry, key: str) -> str | None:
    record = report.records.get(entry.detector) or {}
    text = record.get(key)
    return str(text) if isinstance(text, str) and text else None


def origin_ns(report: Report, entry: ReportEntry) -> int:
    """Time zero of an entry's panels: the log's first sample as ``detect`` recorded it
    (fault and ``--start`` times count from there), else the report's first status
    sample (logs of an older imufdi)."""
    record = report.records.get(entry.detector) or {}
    t0 = record.get("t0_ns")
    return int(t0) if isinstance(t0, int) else int(report.t0_ns)


def smaller_is_worse(entry: ReportEntry) -> bool:
    """Whether this detector isolates the sensor with the *smallest* score (pca-parity's
    angles): judged from the data, at alarm samples where a sensor was isolated."""
    scores, isolated = entry.scores, entry.isolated
    if scores.size == 0 or isolated.size != scores.shape[0]:
        return False
    rows = np.flatnonzero(entry.alarm & (isolated >= 0))
    if rows.size == 0:
        return False
    picked = scores[rows, isolated[rows]]
    finite = np.where(np.isfinite(scores[rows]), scores[rows], np.nan)
    with np.errstate(all="ignore"):
        is_min = np.isclose(picked, np.nanmin(finite, axis=1))
        is_max = np.isclose(picked, np.nanmax(finite, axis=1))
    return int(np.count_nonzero(is_min)) > int(np.count_nonzero(is_max))


def suspects(entry: ReportEntry, limit: int = SUSPECTS) -> list[int]:
    """Sensor indices to draw one by one: every truly faulty one, then those most often
    isolated during alarms (up to ``limit`` in all, at least one wrongly isolated sensor
    when there is one)."""
    truth = [int(j) for j in np.flatnonzero(entry.faulty.any(axis=0))] if entry.faulty.size else []
    chosen = list(truth)
    room = max(limit - len(truth), 1) if truth else 1  # no fault: the worst false one
    if entry.isolated.size and entry.alarm.size == entry.isolated.size:
        hits = entry.isolated[entry.alarm & (entry.isolated >= 0)]
        counts = np.bincount(hits, minlength=len(entry.sensor_ids))
        for j in np.argsort(-counts, kind="stable"):
            if room == 0 or counts[j] == 0:
                break
            if int(j) not in chosen:
                chosen.append(int(j))
                room -= 1
    return chosen


def envelope(values: np.ndarray, columns: int) -> np.ndarray:
    """Indices of the samples of a line that its drawing at ``columns`` pixel columns needs.

    A line of at most ``2 * columns`` samples is kept whole. A longer one is cut into
    ``columns`` (or fewer) runs of equal sample count; of each run the sample with the
    smallest and the one with the largest value are kept (a min/max envelope: every spike,
    however short, stays on the figure, unlike plain striding), and the run's first NaN if
    it has one (a gap in the line stays a gap), with the first and last sample of the line.

    Parameters
    ----------
    values : ndarray, shape (n,)
        The line's values (NaN: no value, drawn as a gap).
    columns : int
        Pixel columns the line spans at most (>= 1).

    Returns
    -------
    ndarray of int, shape (m,)
        Sorted sample indices, ``m <= 3 * columns + 2``; ``arange(n)`` for a short line.
    """
    y = np.asarray(values, float)
    n = y.size
    if n <= 2 * columns:
        return np.arange(n)
    per = -(-n // columns)  # samples per run
    runs = -(-n // per)
    padded = np.full(runs * per, np.nan)
    padded[:n] = y
    rows = padded.reshape(runs, per)
    gap = np.isnan(rows)
    low = np.argmin(np.where(gap, np.inf, rows), axis=1)
    high = np.argmax(np.where(gap, -np.inf, rows), axis=1)
    gap.reshape(-1)[n:] = False  # the padding is no gap
    has_gap = gap.any(axis=1)
    first_gap = np.argmax(gap, axis=1)[has_gap]
    start = np.arange(runs) * per
    keep = np.concatenate(
        [start + low, start + high, start[has_gap] + first_gap, np.array([0, n - 1])]
    )
    return np.unique(np.minimum(keep, n - 1))


def _band_envelope(
    t: np.ndarray, low: np.ndarray, high: np.ndarray, columns: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A band (``low`` to ``high`` at times ``t``) reduced to ``columns`` runs of equal
    sample count: each run spans its first to its last time, from the smallest ``low`` to
    the largest ``high`` in it (NaN ignored; an all-NaN run stays NaN: a gap). Short
    bands (at most ``2 * columns`` samples) are returned whole. Shapes (m,) each."""
    n = t.size
    if n <= 2 * columns:
        return t, low, high
    per = -(-n // columns)
    starts = np.arange(0, n, per)
    ends = np.minimum(starts + per, n) - 1
    with np.errstate(all="ignore"):
        lo = np.fmin.reduceat(low, starts)
        hi = np.fmax.reduceat(high, starts)
    x = np.column_stack([t[starts], t[ends]]).ravel()
    return x, np.repeat(lo, 2), np.repeat(hi, 2)


def _row_quantiles(values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """10th percentile, median and 90th percentile of every row of ``values``, NaN
    ignored (as ``np.nanpercentile`` / ``np.nanmedian`` row by row, same numbers), NaN
    for rows without a finite value.

    Rows are grouped by their count of non-NaN values; each group is one vectorised
    ``np.percentile`` / ``np.median`` call on its rows sorted with the NaNs cut off,
    instead of one call per row (at most 40 000 rows, usually one group).

    Parameters
    ----------
    values : ndarray, shape (n, k)

    Returns
    -------
    low, mid, high : ndarray, shape (n,)
    """
    n = values.shape[0]
    low, mid, high = (np.full(n, np.nan) for _ in range(3))
    ok = np.isfinite(values).any(axis=1)
    if not ok.any():
        return low, mid, high
    rows = np.sort(values[ok], axis=1)  # NaN last
    counts = np.count_nonzero(~np.isnan(rows), axis=1)
    where = np.flatnonzero(ok)
    with np.errstate(all="ignore"):  # rows with infinities: NaN quantiles, as before
        for count in np.unique(counts):
            group = counts == count
            part = rows[group, :count]
            ten, ninety = np.percentile(part, [10, 90], axis=1)
            low[where[group]] = ten
            high[where[group]] = ninety
            mid[where[group]] = np.median(part, axis=1)
    return low, mid, high


def _shade_faults(ax: Any, t: np.ndarray, entry: ReportEntry, label: bool) -> None:
    shade = np.asarray(entry.faulty.any(axis=1) if entry.faulty.size else np.zeros(t.size, bool))
    if shade.any():
        # the first and last sample of every run of shade and of no shade draw the same
        # regions (first to last shaded sample each) as every sample
        change = np.flatnonzero(np.diff(shade.view(np.int8), prepend=2, append=2))
        keep = np.unique(np.clip(np.concatenate([change, change - 1]), 0, t.size - 1))
        ax.fill_between(
            t[keep],
            0,
            1,
            where=shade[keep],
            transform=ax.get_xaxis_transform(),
            color=FAULT_COLOUR,
            alpha=0.10,
            lw=0,
            label="fault (truth)" if label else None,
            step="post",
        )


def _shade_calibration(
    ax: Any, report: Report, entry: ReportEntry, t0_ns: int, label: bool
) -> None:
    """Hatch the detector's calibration window (``calibration_window_ns`` of its
    ``imufdi.detect.<name>`` record): the samples it learnt from, in sample, never scored."""
    record = report.records.get(entry.detector) or {}
    window = record.get("calibration_window_ns")
    if not (isinstance(window, (list, tuple)) and len(window) == 2):
        return
    try:
        start, end = ((int(v) - t0_ns) / 1e9 for v in window)
    except (TypeError, ValueError):
        return
    ax.axvspan(
        start,
        end,
        facecolor="none",
        edgecolor=CALIBRATION_COLOUR,
        hatch="///",
        lw=0,
        alpha=0.6,
        zorder=0.5,
        label="calibration (in sample)" if label else None,
    )


def _alarm_runs(ax: Any, t: np.ndarray, alarm: np.ndarray) -> int:
    """Alarms as runs (first to last sample of each) in the bottom lane; returns how many."""
    from imufdi_cli.episodes import find_episodes

    runs = find_episodes(np.asarray(alarm, bool))
    if not runs:
        return 0
    period = float(np.median(np.diff(t))) if t.size > 1 else 0.0
    spans = [(t[a], max(t[b - 1] - t[a], 0.0) + period) for a, b in runs]
    low, high = ALARM_LANE
    ax.broken_barh(
        spans,
        (low, high - low),
        transform=ax.get_xaxis_transform(),
        color=ALARM_COLOUR,
        lw=0,
    )
    return len(runs)


def episode_label(episode: dict[str, Any]) -> str:
    """``imu3.gyro.x: step 0.9 °/s [0.85, 0.95]``: the sensor, class and size."""
    sensor = (episode.get("sensors") or ["?"])[0]
    size = format_size(episode)
    text = f"{sensor}: {episode.get('fault_class') or 'unexplained'}"
    return text if size == "-" else f"{text} {size}"


def place_labels(
    starts: Sequence[float], widths: Sequence[float], rows: int, gap: float = 0.006
) -> list[tuple[float, int] | None]:
    """Where labels go so that none overlaps another, no leader line crosses one, and none
    leaves the panel.

    Label i belongs at ``starts[i]`` (axes fraction; its leader line drops from there to
    the lane below row 0) and is ``widths[i]`` wide; it starts there, moved left when it
    would pass the right edge, in the lowest of ``rows`` rows where it overlaps no label
    already placed (with ``gap`` between), no label of a lower row covers its leader, and
    it covers no leader of a label of a higher row. Labels are placed in the order given
    (most important first); one that fits in no row gets None.

    Returns
    -------
    list of (x, row) or None
        The left edge (axes fraction, in [0, 1 - width]) and row of each label.
    """
    placed: list[tuple[float, float, float, int]] = []  # (left, right, anchor, row)
    out: list[tuple[float, int] | None] = []
    for start, width in zip(starts, widths):
        if width > 1.0:
            out.append(None)
            continue
        anchor = min(max(float(start), 0.0), 1.0)
        x = min(max(float(start), 0.0), 1.0 - width)
        spot = None
        for row in range(rows):
            clear = all(
                (r != row or x + width + gap <= a or b + gap <= x)
                and (r >= row or not a - gap <= anchor <= b + gap)  # its leader
                and (r <= row or not x - gap <= c <= x + width + gap)  # their leaders
                for a, b, c, r in placed
            )
            if clear:
                spot = (x, row)
                placed.append((x, x + width, anchor, row))
                break
        out.append(spot)
    return out


@dataclass
class EpisodeMarks:
    """What :func:`_mark_episodes` drew on a panel."""

    drawn: int = 0  # episode bars
    labelled: int = 0
    lane: tuple[float, float] = (0.0, 0.0)  # the bars' lane, axes fraction
    labels: list[Any] = field(default_factory=list)  # the label artists


def _mark_episodes(
    ax: Any, report: Report, entry: ReportEntry, t0_ns: int, renderer: Any
) -> EpisodeMarks:
    """Draw this detector's episodes as bars in a lane under the legend, label as many of
    the explained ones as fit (longest first: sensor, class and size, :func:`place_labels`)
    in rows between the lane and the legend, and raise the panel's top so that the data
    stay below the lane. Needs the panel laid out (sizes in pixels)."""
    mine = [
        ep
        for ep in report.episodes
        if ep["detector"] == entry.detector and ep["sensor_type"] == entry.sensor_type
    ]
    # every episode's bar (the report lists the first EPISODES_LISTED with their
    # explanation; older Report objects have only those)
    spans = report.episode_spans.get((entry.detector, entry.sensor_type)) or [
        (ep["start_ns"], ep["end_ns"]) for ep in mine
    ]
    marks = EpisodeMarks()
    if not spans:
        return marks
    to_axes = ax.transAxes.inverted()
    legend = ax.get_legend()
    ceiling = 0.99
    if legend is not None:
        ceiling = float(legend.get_window_extent(renderer).transformed(to_axes).y0) - 0.01
    order = sorted(range(len(mine)), key=lambda i: -(mine[i]["end_ns"] - mine[i]["start_ns"]))
    texts = [episode_label(mine[i]) for i in order]
    widths, height = [], 0.0
    for text in texts:
        probe = ax.text(0, 0, text, fontsize=7, transform=ax.transAxes)
        box = probe.get_window_extent(renderer).transformed(to_axes)
        widths.append(float(box.width))
        height = max(height, float(box.height))
        probe.remove()
    rows = EPISODE_LABEL_ROWS if texts else 0
    row_step = height + 0.012
    high = ceiling - rows * row_step - 0.01
    low = high - EPISODE_LANE_HEIGHT
    marks.lane = (low, high)
    _keep_data_below(ax, low - 0.03)
    x0, x1 = ax.get_xlim()
    span = (x1 - x0) or 1.0
    minimum = span / 400.0  # a one-sample episode stays visible
    ax.broken_barh(
        [((a - t0_ns) / 1e9, max((b - a) / 1e9, minimum)) for a, b in spans],
        (low, high - low),
        transform=ax.get_xaxis_transform(),
        color="#8c6d1f",
        lw=0,
        alpha=0.8,
    )
    marks.drawn = len(spans)
    starts = [((mine[i]["start_ns"] - t0_ns) / 1e9 - x0) / span for i in order]
    for start, text, spot in zip(starts, texts, place_labels(starts, widths, rows)):
        if spot is None:
            continue
        x, row = spot
        marks.labels.append(
            ax.annotate(
                text,
                xy=(min(max(start, 0.0), 1.0), high),
                xycoords="axes fraction",
                xytext=(x, high + 0.01 + row * row_step),
                textcoords="axes fraction",
                fontsize=7,
                va="bottom",
                ha="left",
                color="#5a3d00",
                arrowprops={
                    "arrowstyle": "-",
                    "color": "#8c6d1f",
                    "lw": 0.6,
                    "shrinkA": 0,
                    "shrinkB": 0,
                    "relpos": (0.0, 0.0),  # from the label's lower left corner
                },
                annotation_clip=False,
            )
        )
    marks.labelled = len(marks.labels)
    if marks.drawn > marks.labelled:
        ax.text(
            0.995,
            low - 0.01,
            f"{marks.drawn - marks.labelled} of {marks.drawn} episodes not labelled"
            " (imufdi report -v lists them)",
            transform=ax.transAxes,
            fontsize=6.5,
            ha="right",
            va="top",
            color="#5a3d00",
        )
        _keep_data_below(ax, low - 0.03 - height)
    return marks


def _keep_data_below(ax: Any, fraction: float) -> None:
    """Raise the panel's top so that its current data range ends at ``fraction`` of its
    height (linear or log axis); nothing when it already does."""
    bottom, top = ax.get_ylim()
    data_top = ax.dataLim.y1
    if not np.isfinite(data_top) or fraction <= 0.05:
        return
    if ax.get_yscale() == "log" and bottom > 0 and data_top > 0:
        now = (np.log(data_top) - np.log(bottom)) / (np.log(top) - np.log(bottom))
        if now > fraction:
            ax.set_ylim(bottom, bottom * (data_top / bottom) ** (1.0 / fraction))
    else:
        now = (data_top - bottom) / ((top - bottom) or 1.0)
        if now > fraction:
            ax.set_ylim(bottom, bottom + (data_top - bottom) / fraction)


def use_log_scale(statistic: np.ndarray, threshold: np.ndarray) -> bool:
    """Whether a statistic is drawn on a log axis: its positive values span more than
    :data:`LOG_SPREAD`, or its peak exceeds the median finite threshold
    :data:`LOG_OVER_THRESHOLD` times."""
    stat = np.asarray(statistic, float)
    thr = np.asarray(threshold, float)
    positive = stat[np.isfinite(stat) & (stat > 0)]
    if positive.size == 0:
        return False
    finite_thr = thr[np.isfinite(thr) & (thr > 0)]
    spread = positive.max() / positive.min()
    over = positive.max() / float(np.median(finite_thr)) if finite_thr.size else 1.0
    return bool(spread > LOG_SPREAD or over > LOG_OVER_THRESHOLD)


def _line(ax: Any, t: np.ndarray, y: np.ndarray, columns: int, **style: Any) -> Any:
    """``ax.plot(t, y, **style)`` of the samples its pixels need (:func:`envelope`)."""
    keep = envelope(y, columns)
    return ax.plot(t[keep], y[keep], **style)


def _statistic_panel(
    ax: Any, report: Report, entry: ReportEntry, t: np.ndarray, columns: int
) -> None:
    colour = detector_colour(entry.detector)
    stat = np.asarray(entry.statistic, float)
    thr = np.asarray(entry.threshold, float)
    _shade_faults(ax, t, entry, label=True)
    positive = stat[np.isfinite(stat) & (stat > 0)]
    log = use_log_scale(stat, thr)
    if log:
        floor = max(positive.min(), positive.max() * 1e-6)
        ax.set_yscale("log")
        stat = np.where(np.isfinite(stat), np.maximum(stat, floor), np.nan)
    _shade_calibration(ax, report, entry, origin_ns(report, entry), label=True)
    dense = t.size > 2 * columns
    _line(
        ax,
        t,
        stat,
        columns,
        lw=0.8,
        color=colour,
        alpha=0.45 if dense else 1.0,
        label="statistic (min-max per px)" if dense else "statistic",
    )
    if dense:  # the envelope of a long log is a band: its median per pixel on top
        bt, mid = _binned_median(t, stat, columns // 2)
        ax.plot(bt, mid, lw=0.9, color=colour, label="median per px")
    thr = np.where(np.isfinite(thr), thr, np.nan)
    _line(ax, t, thr, columns, color="k", ls="--", lw=1.0, label="threshold")
    runs = _alarm_runs(ax, t, entry.alarm) if entry.alarm.size else 0
    if runs:
        share = 100.0 * np.count_nonzero(entry.alarm) / max(entry.alarm.size, 1)
        ax.plot([], [], lw=5, color=ALARM_COLOUR, label=f"alarm ({share:.1f} % of samples)")
    if any(
        ep["detector"] == entry.detector and ep["sensor_type"] == entry.sensor_type
        for ep in report.episodes
    ):
        ax.plot([], [], lw=5, color="#8c6d1f", alpha=0.8, label="episode")
    unit = "log scale" if log else "linear"
    ax.set_ylabel(f"statistic, dimensionless\n({unit})", fontsize=8)
    described = _described(report, entry, "statistic")
    title = f"{entry.detector} · {entry.sensor_type}: detection statistic"
    ax.set_title(title, fontsize=10, color=colour, loc="left")
    if described:
        ax.set_title(_wrap(described, 60), fontsize=7, loc="right", color="0.35")
    _headroom(ax, STATISTIC_HEADROOM)
    ax.legend(loc="upper left", fontsize=7, framealpha=0.85, ncol=4)


def _binned_median(t: np.ndarray, y: np.ndarray, bins: int) -> tuple[np.ndarray, np.ndarray]:
    """The median of ``y`` (NaN ignored) in ``bins`` runs of equal sample count, at each
    run's middle time; NaN for a run without a value. Shapes (m,), m <= bins."""
    n = y.size
    per = max(1, -(-n // max(bins, 1)))
    runs = -(-n // per)
    padded = np.full(runs * per, np.nan)
    padded[:n] = y
    rows = padded.reshape(runs, per)
    starts = np.arange(runs) * per
    middle = t[np.minimum(starts + per // 2, n - 1)]
    ok = np.isfinite(rows).any(axis=1)
    out = np.full(runs, np.nan)
    if ok.any():
        mid = _row_quantiles(rows[ok])[1]
        out[ok] = mid
    return middle, out


def _binned_quantiles(
    t: np.ndarray, y: np.ndarray, bins: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """10th percentile, median and 90th percentile of ``y`` in ``bins`` runs of equal
    sample count, at each run's middle time (NaN where a run has no value)."""
    n = y.size
    per = max(1, -(-n // max(bins, 1)))
    runs = -(-n // per)
    padded = np.full(runs * per, np.nan)
    padded[:n] = y
    low, mid, high = _row_quantiles(padded.reshape(runs, per))
    middle = t[np.minimum(np.arange(runs) * per + per // 2, n - 1)]
    return middle, low, mid, high


def _isolation_panel(
    ax: Any, report: Report, entry: ReportEntry, t: np.ndarray, columns: int
) -> None:
    scores = np.asarray(entry.scores, float)
    _shade_faults(ax, t, entry, label=False)
    _shade_calibration(ax, report, entry, origin_ns(report, entry), label=False)
    ax.set_title(
        f"{entry.detector} · {entry.sensor_type}: isolation scores", fontsize=10, loc="left"
    )
    if not scores.size or not np.isfinite(scores).any():
        ax.text(0.5, 0.5, "no isolation scores", ha="center", va="center", transform=ax.transAxes)
        ax.set_yticks([])
        return
    flip = smaller_is_worse(entry)
    chosen = suspects(entry)
    if not flip and use_log_scale(scores, np.zeros(0)):
        ax.set_yscale("log")  # e.g. glt's D_FI: 1e6 in saturation, ~1 otherwise
        positive = scores[np.isfinite(scores) & (scores > 0)]
        scores = np.where(
            np.isfinite(scores),
            # dips below the 10th percentile (a score crossing zero) carry no information
            # on a log axis and would fill the panel down to them
            np.maximum(scores, float(np.percentile(positive, 10.0))),
            np.nan,
        )
    others = [j for j in range(scores.shape[1]) if j not in chosen]
    if others:
        low, mid, high = _row_quantiles(scores[:, others])
        ax.fill_between(
            *_band_envelope(t, low, high, columns),
            color="0.6",
            alpha=0.35,
            lw=0,
            label=f"other {len(others)} sensors, 10-90 %",
        )
        _line(ax, t, mid, columns, color="0.45", lw=0.6, label="other sensors, median")
    truth = set(np.flatnonzero(entry.faulty.any(axis=0)).tolist()) if entry.faulty.size else set()
    styles = ["-", "--", ":", "-."]
    palette = SUSPECT_COLOURS
    reds = ("#d62728", "#8c1515", "#ff7f7f")
    n_truth = 0
    for k, j in enumerate(chosen):
        faulty = j in truth
        if faulty:
            colour, style, width = reds[n_truth % 3], styles[n_truth % 3], 1.2
            n_truth += 1
        else:
            colour = palette[(k - n_truth) % len(palette)]
            style, width = styles[((k - n_truth) % 3) + 1], 0.9
        name = f"{entry.sensor_ids[j]}" + (" (faulty, truth)" if faulty else " (isolated)")
        if t.size > 2 * ISOLATION_BINS:  # a bin's median and 10-90 % band: readable
            bt, _, mid, _ = _binned_quantiles(t, scores[:, j], ISOLATION_BINS)
            name += f", median of {-(-t.size // ISOLATION_BINS)}"
            ax.plot(
                bt,
                mid,
                lw=width + 0.3,
                ls=style,
                color=colour,
                label=name,
                zorder=3 if faulty else 2,
                drawstyle="steps-mid",
            )
        else:
            _line(
                ax,
                t,
                scores[:, j],
                columns,
                lw=width,
                ls=style,
                color=colour,
                label=name,
                zorder=3 if faulty else 2,
            )
    described = _described(report, entry, "scores")
    label = described or "isolation score"
    if flip:
        ax.invert_yaxis()
        label += "; axis inverted: smaller = more suspect, drawn up"
    ax.set_ylabel(_wrap(label, 45), fontsize=7)
    _headroom(ax)
    ax.legend(loc="upper left", fontsize=7, framealpha=0.85, ncol=2)


def figure_report(report: Report) -> Any:
    """The figure of :func:`plot_report` (a matplotlib Figure, not yet saved; close it
    with ``pyplot().close(fig)``).

    Lines longer than twice the figure's width in pixels are drawn from their min/max
    envelope (:func:`envelope`): what the pixels can show, every spike kept."""
    plt = pyplot()
    entries = report.entries
    fig, axes = plt.subplots(
        len(entries),
        2,
        figsize=(ROW_WIDTH_IN, 3.4 * len(entries)),
        squeeze=False,
        constrained_layout=True,
    )
    columns = int(ROW_WIDTH_IN * DPI)  # wider than either panel
    for row, entry in enumerate(entries):
        t = (entry.t_ns - origin_ns(report, entry)) / 1e9
        _statistic_panel(axes[row][0], report, entry, t, columns)
        _isolation_panel(axes[row][1], report, entry, t, columns)
        for ax in axes[row]:
            ax.set_xlabel("time since the log start, s", fontsize=8)
            ax.tick_params(labelsize=8)
            ax.grid(True, which="major", alpha=0.25)
    fig.suptitle(f"imufdi report: {report.source}", fontsize=11)
    # the episode labels are placed on the laid-out panels (their width in pixels)
    engine = fig.get_layout_engine()
    if engine is not None:
        engine.execute(fig)
    renderer = fig.canvas.get_renderer()
    for row, entry in enumerate(entries):
        _mark_episodes(axes[row][0], report, entry, origin_ns(report, entry), renderer)
    return fig


def plot_report(report: Report, path: str) -> None:
    """Detection statistic vs threshold with alarms, and isolation scores of the suspect
    sensors, over time, faults shaded, from the series kept with
    ``build_report(keep_series=True)``; one row per detector and sensor type."""
    plt = pyplot()
    fig = figure_report(report)
    try:
        save_figure(fig, path, DPI)
    finally:
        plt.close(fig)


def plot_roc(report: Report, path: str) -> None:
    """MAR against FAR of every swept entry (log FAR axis), the matched FAR marked;
    colour per detector, line style per sensor type."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.5, 4.5), constrained_layout=True)
    styles = {"gyro": "-", "accel": "--", "mag": ":"}
    for e in report.entries:
        if e.roc is None:
            continue
        far, mar = e.roc["far"], e.roc["mar"]
        ok = ~np.isnan(far) & ~np.isnan(mar) & (far > 0)
        if not ok.any():  # no faulty samples of this type: nothing to draw or list
            continue
        ax.plot(
            far[ok] * 100,
            mar[ok] * 100,
            lw=1.2,
            color=detector_colour(e.detector),
            ls=styles.get(e.sensor_type, "-."),
            label=f"{e.detector} · {e.sensor_type}",
        )
    if report.match_far is not None:
        ax.axvline(report.match_far * 100, color="k", ls="--", lw=0.8, label="matched FAR")
    ax.set_xscale("log")
    ax.set_xlabel("FAR, % of fault-free samples outside the calibration window")
    ax.set_ylabel("MAR, % of faulty samples")
    ax.set_title("threshold sweep of the raw statistic")
    ax.grid(True, which="both", alpha=0.25)
    ax.legend(fontsize=8)
    try:
        save_figure(fig, path, DPI)
    finally:
        plt.close(fig)
