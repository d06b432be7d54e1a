"""The rich-free rendering of the commands' tables (``info``, ``report``, ``detect``,
``calibrate``, ``tune``, ``ingest``, ``demo``) is byte for byte what rich prints in a pipe."""

from __future__ import annotations

import io
import string
import sys
from types import SimpleNamespace

import numpy as np
import pytest

from imufdi_cli.cli import ui
from imufdi_cli.cli.data import ingest_table
from imufdi_cli.cli.describe import render_info, render_info_plain
from imufdi_cli.cli.detection import calibrate_table, convergence_table, detect_table
from imufdi_cli.cli.plain import PLAIN_WIDTH, PlainTable
from imufdi_cli.cli.reporting import episode_tables, report_table
from imufdi_cli.cli.ui import make_console

ALPHABET = string.ascii_letters + string.digits + " ./_-:(){},%+=[]@#"
#: markup-like text: every table text is escaped for rich, so these read as they are
MARKUP = ("[b]", "[/]", "[bold red]", "[0.88, 0.94]", "[inf, 3]", "[@click]", "[#f00]", "]")
UNSAFE = ("é", "→", "\t", " ", "\\", "\\[b]")


def rich_text(draw) -> str:
    """What a plain (non-terminal) console of the CLI prints for ``draw(console)``."""
    buffer = io.StringIO()
    draw(make_console(io.StringIO(), buffer))  # a StringIO is not a terminal
    return buffer.getvalue()


def random_cell(rng: np.random.Generator) -> str:
    n = int(rng.integers(0, 30)) if rng.random() < 0.9 else int(rng.integers(30, 90))
    text = "".join(ALPHABET[int(i)] for i in rng.integers(0, len(ALPHABET), n)).strip()
    if rng.random() < 0.1:
        text += MARKUP[int(rng.integers(0, len(MARKUP)))]
    if rng.random() < 0.05:  # something only rich renders: the table must defer
        text += UNSAFE[int(rng.integers(0, len(UNSAFE)))]
    return text


@pytest.mark.parametrize("boxed", [True, False])
def test_random_tables_render_as_rich_or_defer(boxed: bool) -> None:
    """Random tables: 1-5 columns each left- or right-justified (so mixed), 0-4 rows,
    with or without a title, cells of printable ASCII with markup-like brackets."""
    rng = np.random.default_rng(21)
    rendered = right = empty = 0
    for _ in range(300):
        n_cols = int(rng.integers(1, 6))
        title = random_cell(rng) if rng.random() < 0.8 else None
        justify = ["right" if rng.random() < 0.5 else "left" for _ in range(n_cols)]
        table = PlainTable(
            [random_cell(rng) for _ in range(n_cols)], boxed=boxed, title=title, justify=justify
        )
        for _ in range(int(rng.integers(0, 5))):
            table.add_row(*(random_cell(rng) for _ in range(n_cols)))
        text = table.render()
        if text is None:
            continue
        rendered += 1
        right += "right" in justify
        empty += not table.rows
        assert text == rich_text(lambda c, t=table: c.print(t.to_rich()))
    # the comparison ran on many tables, right-justified columns and (boxed) empty tables
    assert rendered > 50 and right > 25 and (empty > 5 or not boxed)


def test_too_wide_or_unsafe_tables_defer_to_rich() -> None:
    wide = PlainTable(("a", "b"))
    wide.add_row("x" * PLAIN_WIDTH, "y")
    assert wide.render() is None
    for cell in ("é", "tab\there", " lead", "back\\slash", "x\\[b]"):
        table = PlainTable(("a",))
        table.add_row(cell)
        assert table.render() is None, cell
    assert PlainTable(("a",), boxed=False).render() is None  # no rows, no box: rich's call


def test_markup_is_text_in_both_renderings() -> None:
    table = PlainTable(("size [90 %]", "[b]x"), title="[red]t[/red]", justify=("right",))
    table.add_row("0.91 deg/s [0.88, 0.94]", "[bold]x[/bold]")
    text = table.render()
    assert text is not None and "[bold]x[/bold]" in text and text.startswith("[red]t[/red]\n")
    assert text == rich_text(lambda c: c.print(table.to_rich()))


def test_justify_must_name_left_or_right_per_column() -> None:
    with pytest.raises(ValueError, match="justify"):
        PlainTable(("a",), justify=("center",))
    with pytest.raises(ValueError, match="justify"):
        PlainTable(("a",), justify=("left", "right"))


# --- the commands' tables -----------------------------------------------------------------


def assert_renders_as_rich(table: PlainTable) -> str:
    text = table.render()
    assert text is not None, table.title  # the command's usual table prints without rich
    assert text == rich_text(lambda c: c.print(table.to_rich()))
    return text


def test_report_in_a_pipe_is_what_rich_prints(cli, detected_log, monkeypatch) -> None:
    """``imufdi report LOG | ...``: the figure table and both episode tables (brackets in
    the size column) as rich renders the same report, without making a rich console; the
    demo's table from the same report too."""
    from imufdi_cli import report as rep
    from imufdi_cli.cli.demo import demo_table

    built = []
    build = rep.build_report
    monkeypatch.setattr(
        rep, "build_report", lambda *a, **k: built.append(build(*a, **k)) or built[-1]
    )
    made = []
    monkeypatch.setattr(ui, "make_console", lambda *a, **k: made.append(a))
    result = cli(["report", detected_log])
    assert result.code == 0, result.stderr
    assert made == []  # no rich console: rich is not even imported for this in a pipe
    monkeypatch.undo()
    report = built[0]
    tables = [report_table(report), *episode_tables(report, limit=12)]
    assert len(tables) == 3 and all(t.render() is not None for t in tables)
    assert "[" in tables[2].rows[0][5]  # an interval in brackets, escaped for rich
    assert result.out == rich_text(lambda c: [c.print(t.to_rich()) for t in tables])
    assert_renders_as_rich(demo_table(report))


def test_detect_tune_calibrate_ingest_tables_are_what_rich_prints() -> None:
    from imufdi_cli.calibrate.triads import TriadFigures
    from imufdi_cli.capture.stats import IngestStats
    from imufdi_cli.detect import TypeSummary

    gyro = TypeSummary(500, 174, 67, {"imu0.gyro.x": 151, "imu2.gyro.x": 2, "imu3.gyro.y": 2})
    gyro.episodes = {"none": 2, "drift": 3, "step": 1}
    summaries = {"glt": {"gyro": gyro, "accel": TypeSummary(500)}}
    detected = SimpleNamespace(samples=500, duration_s=4.99, summaries=summaries)
    text = assert_renders_as_rich(detect_table(detected, "out [b].mcap"))
    assert "-> out [b].mcap" in text and "imu0.gyro.x (151), imu2.gyro.x (2), imu3" in text
    assert "drift 3, none 2, step 1" in text
    assert_renders_as_rich(convergence_table([1.33474, 1.32717, 1.30949e-5]))
    figures = [
        TriadFigures(0, "gyro", [-843.2, -6718.0, 200.4], 10.45, [-0.0244, -0.0048, 0.0]),
        TriadFigures(0, "accel", [-6001.0, 8364.0, 465.0], 3.94, [-0.2792, -0.1244, 0.5326]),
    ]
    text = assert_renders_as_rich(calibrate_table(SimpleNamespace(figures=figures), "a", "b"))
    assert "-1.3980 -0.2750 +0.0000 deg/s" in text
    stats = IngestStats(bytes_total=117807, frames_ok=497, frames_lost=3, n_imus=16)
    assert_renders_as_rich(ingest_table("cap.bin", "out.mcap", stats.as_rows()))


def test_a_table_rich_must_render_defers_to_it(monkeypatch) -> None:
    """A cell rich treats specially (non-ASCII here) makes the command print through
    rich; the output is then rich's, in a pipe as on the stream the summary goes to."""
    summaries = {
        "glt": {"gyro": SimpleNamespace(samples=1, alarms=0, events=0, isolated={}, episodes={})}
    }
    table = detect_table(SimpleNamespace(samples=1, duration_s=0.01, summaries=summaries), "é.mcap")
    assert table.render() is None
    err = io.StringIO()
    monkeypatch.setattr(sys, "stderr", err)
    out = ui.UI()
    out.print_table(table, summary=True)
    out.flush()
    assert err.getvalue() == rich_text(lambda c: c.print(table.to_rich()))
    assert "-> é.mcap" in err.getvalue()


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


@pytest.mark.parametrize("summary", [False, True])
def test_print_table_in_order_through_rich_on_a_terminal(monkeypatch, summary: bool) -> None:
    """In a pipe: plain text in order with the console's lines; on a terminal (40
    columns here): rich's rendering, never the plain text; nothing with --quiet."""
    table = PlainTable(("name", "value"), title="t", justify=("left", "right"))
    table.add_row("a long enough name", "a value long enough to wrap at 40 columns")
    streams = {"stdout": io.StringIO(), "stderr": io.StringIO()}
    target = "stderr" if summary else "stdout"
    for name, stream in streams.items():
        monkeypatch.setattr(sys, name, stream)
    out = ui.UI()
    console = out.summary if summary else out.product
    console.print("before")
    out.print_table(table, summary=summary)
    console.print("after")
    out.flush()
    assert streams[target].getvalue() == f"before\n{table.render()}after\n"
    monkeypatch.setenv("COLUMNS", "40")
    monkeypatch.setenv("NO_COLOR", "1")  # no styles to compare, the terminal's width
    terminal = Terminal()
    monkeypatch.setattr(sys, target, terminal)
    out = ui.UI()
    out.print_table(table, summary=summary)
    out.flush()
    expected = io.StringIO()
    make_console(Terminal(), expected).print(table.to_rich())
    assert terminal.getvalue() == expected.getvalue() != table.render()
    quiet = ui.UI(quiet=True)
    quiet.print_table(table, summary=summary)
    quiet.flush()
    assert terminal.getvalue() == expected.getvalue()  # nothing more


def test_print_table_on_a_console() -> None:
    """``print_table(console, table)`` (demo's live console): plain text on a plain
    console, rich on a terminal one, nothing on a quiet one."""
    table = PlainTable(("k", "v"), justify=("right", "left"))
    table.add_row("x", "[b]y")
    plain = io.StringIO()
    ui.print_table(make_console(io.StringIO(), plain), table)
    assert plain.getvalue() == table.render() == rich_text(lambda c: c.print(table.to_rich()))
    quiet = io.StringIO()
    ui.print_table(make_console(io.StringIO(), quiet, quiet=True), table)
    assert quiet.getvalue() == ""
    styled = io.StringIO()
    ui.print_table(make_console(Terminal(), styled), table)
    expected = io.StringIO()
    make_console(Terminal(), expected).print(table.to_rich())
    assert styled.getvalue() == expected.getvalue()


def full_summary() -> dict:
    """An info summary with every optional part."""
    return {
        "source": "logs/run 1.mcap",
        "n_imus": 3,
        "n_samples": 1200,
        "duration_s": 11.99,
        "start_ns": 1700000000000000000,
        "rate_hz": 100.0000001,
        "rate_method": "(1200 aligned samples + 0 missing - 1) / 11.99 s",
        "time_source": "log_time",
        "imu_fields": {"/a": "imu", "/b": None},
        "gaps": {"count": 2, "missing_samples": 3, "expected_samples": 1203, "longest_s": 0.02},
        "ingest": {"frames_ok": 1200, "frames_lost": 3, "duplicates": 1, "bytes_dropped": 9},
        "alignment": {"n_aligned": 1200, "messages": {"/a": 1200, "/b": 0}, "late": {"/a": 2}},
        "topics": [
            {"topic": "/a", "schema": "x/Imu", "message_encoding": "cdr", "message_count": 1200},
            {"topic": "/b", "schema": None, "message_encoding": "json", "message_count": 0},
        ],
        "array": {
            "imu": [{"gyro_bias": [0, 0, 0]}, {}],
            "noise": {"gyro": 0.001},
            "range": {"gyro": 4.0},
        },
        "array_from_metadata": True,
        "validity": {"gyro": {"clipped": 1, "invalid": 2, "rows": 1200}},
        "faults": [{"id": "f0", "spec": "step:imu0.gyro.x,at=1s,amp=0.9deg/s"}, {"id": "f1"}],
        "detectors": {
            "glt": {"params": {"alpha": 0.001}, "validity": {"gyro": {"clipped": 0}}},
            "bank": {"params": {}},
        },
    }


def test_info_description_matches_rich() -> None:
    summary = full_summary()
    text = render_info_plain(summary)
    assert text is not None
    assert text == rich_text(lambda c: render_info(c, summary))


def test_info_with_markup_or_unicode_defers_to_rich() -> None:
    summary = full_summary()
    summary["faults"] = [{"id": "f0", "spec": "note [bold]x[/bold] → y"}]
    assert render_info_plain(summary) is None


def test_info_in_a_pipe_does_not_import_rich(fresh_imufdi, table4_log) -> None:
    # a fresh interpreter with stdout on a pipe (tests/cli/conftest.py: shared with test_app.py)
    run = fresh_imufdi(["info", table4_log])
    assert sorted(m for m in run.modules if m.startswith("rich")) == []
    assert "/imu15/data_raw" in run.stdout


@pytest.mark.parametrize("product", [False, True])
def test_notes_and_warnings_in_a_pipe_are_what_rich_prints(monkeypatch, product: bool) -> None:
    """A note or warning on a stream that is not a terminal is the line rich prints (its
    markup escaped, never wrapped), written without rich; text rich would change (a
    backslash, a tab, non-ASCII) goes through rich."""
    texts = [
        "no ground truth in this log (inject faults with `imufdi inject`): FAR, MAR [x]",
        "a long line " + "x" * 300 + " [bold]not markup[/]",
    ]
    made = []
    real = ui.make_console
    monkeypatch.setattr(ui, "make_console", lambda *a, **k: made.append(a) or real(*a, **k))
    plain = ui.UI()
    plain.note(texts, product=product)
    plain.warn(texts[:1])
    buffer = plain._product_buffer if product else plain._summary_buffer
    assert made == []  # no rich console
    expected = "".join(f"note: {t}\n" for t in texts)
    if product:
        assert buffer.getvalue() == expected
        assert plain._summary_buffer.getvalue() == f"warning: {texts[0]}\n"
    else:
        assert buffer.getvalue() == expected + f"warning: {texts[0]}\n"
    rendered = rich_text(lambda c: [c.print(f"[yellow]note:[/] {ui._escape(t)}") for t in texts])
    assert rendered == expected
    unsafe = ui.UI()
    unsafe.note(["a back\\slash"], product=product)
    assert made  # through rich
    assert (unsafe._product_buffer if product else unsafe._summary_buffer).getvalue() == (
        "note: a back\\slash\n"
    )
    quiet = ui.UI(quiet=True)
    quiet.note(texts)
    assert quiet._summary_buffer.getvalue() == ""
