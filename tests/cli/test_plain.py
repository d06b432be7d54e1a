"""The rich-free rendering of ``imufdi info`` is byte for byte what rich prints in a pipe."""

from __future__ import annotations

import io
import string

import numpy as np
import pytest

from imufdi_cli.cli.describe import render_info, render_info_plain
from imufdi_cli.cli.plain import PLAIN_WIDTH, PlainTable
from imufdi_cli.cli.ui import make_console

ALPHABET = string.ascii_letters + string.digits + " ./_-:(){},%+="
UNSAFE = ("[b]", "]", "é", "→", "\t", " ")


def rich_text(draw) -> str:
    """What a plain (non-terminal) console of the CLI prints for ``draw(console)``."""
    buffer = io.StringIO()
    draw(make_console(io.StringIO(), buffer))  # a StringIO is not a terminal
    return buffer.getvalue()


def random_cell(rng: np.random.Generator) -> str:
    n = int(rng.integers(0, 30)) if rng.random() < 0.9 else int(rng.integers(30, 90))
    text = "".join(ALPHABET[int(i)] for i in rng.integers(0, len(ALPHABET), n)).strip()
    if rng.random() < 0.05:  # something only rich renders: the table must defer
        text += UNSAFE[int(rng.integers(0, len(UNSAFE)))]
    return text


@pytest.mark.parametrize("boxed", [True, False])
def test_random_tables_render_as_rich_or_defer(boxed: bool) -> None:
    rng = np.random.default_rng(21)
    rendered = 0
    for _ in range(300):
        n_cols = int(rng.integers(1, 6))
        title = random_cell(rng) if boxed and rng.random() < 0.8 else None
        table = PlainTable([random_cell(rng) for _ in range(n_cols)], boxed=boxed, title=title)
        for _ in range(int(rng.integers(0, 5))):
            table.add_row(*(random_cell(rng) for _ in range(n_cols)))
        text = table.render()
        if text is None:
            continue
        rendered += 1
        assert text == rich_text(lambda c, t=table: c.print(t.to_rich()))
    assert rendered > 50  # the comparison ran on many tables, not only on deferrals


def test_too_wide_or_unsafe_tables_defer_to_rich() -> None:
    wide = PlainTable(("a", "b"))
    wide.add_row("x" * PLAIN_WIDTH, "y")
    assert wide.render() is None
    for cell in ("[bold]x", "é", "tab\there", " lead"):
        table = PlainTable(("a",))
        table.add_row(cell)
        assert table.render() is None, cell


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
