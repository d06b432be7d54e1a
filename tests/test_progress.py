"""Progress callbacks of the library (imufdi_cli.progress) and their use in detect,
inject, ingest and report: called, monotonic, ending at the total."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest

from imufdi_cli.pipeline import SAMPLE_LOGS
from imufdi_cli.progress import LogTimeProgress

SAMPLE = SAMPLE_LOGS / "paper-table4.mcap"


class Recorder:
    def __init__(self) -> None:
        self.calls: list[tuple[float, float | None]] = []

    def __call__(self, done: float, total: float | None) -> None:
        self.calls.append((done, total))

    def check(self, total: float | None) -> None:
        assert self.calls, "the callback was never called"
        done = [d for d, _ in self.calls]
        assert all(b >= a for a, b in itertools.pairwise(done)), "progress went backwards"
        for _, seen in self.calls:
            assert seen == total
        if total is not None:
            assert max(done) <= total * (1 + 1e-9)


def test_log_time_progress_relative_to_the_summary_range():
    rec = Recorder()
    tracker = LogTimeProgress(rec, (1_000_000_000, 3_000_000_000))
    tracker.at(1_500_000_000)
    tracker.at(5_000_000_000)  # past the summary's end: clamped
    tracker.finish()
    assert rec.calls == [(0.5, 2.0), (2.0, 2.0), (2.0, 2.0)]


def test_log_time_progress_two_passes_and_unknown_total():
    rec = Recorder()
    tracker = LogTimeProgress(rec, (0, 2_000_000_000), passes=2)
    tracker.at(1_000_000_000)
    tracker.next_pass()
    tracker.at(1_000_000_000)
    assert rec.calls == [(1.0, 4.0), (3.0, 4.0)]
    rec = Recorder()
    tracker = LogTimeProgress(rec, None)  # a pipe: no summary
    tracker.at(7_000_000_000)
    tracker.at(9_500_000_000)
    tracker.finish()  # nothing to finish against
    assert rec.calls == [(0.0, None), (2.5, None)]


def test_no_callback_is_free():
    tracker = LogTimeProgress(None, (0, 10))
    tracker.at(5)
    tracker.finish()


@pytest.fixture(scope="module")
def faulty(tmp_path_factory) -> Path:
    from imufdi_cli.faults import inject_file

    rec = Recorder()
    out = tmp_path_factory.mktemp("progress") / "faulty.mcap"
    inject_file(SAMPLE, out, ["step:imu0.gyro.x,at=2.5s,amp=0.9deg/s"], [], seed=0, progress=rec)
    rec.check(total=rec.calls[-1][1])
    assert rec.calls[-1][1] == pytest.approx(2 * 4.99, abs=0.02)  # two passes over 4.99 s
    assert rec.calls[-1][0] > 0.9 * rec.calls[-1][1]
    return out


def test_detect_and_report_call_back(faulty, tmp_path):
    from imufdi_cli.detect import detect_file
    from imufdi_cli.report import build_report

    rec = Recorder()
    out = tmp_path / "d.mcap"
    detect_file(faulty, out, [("glt", {})], progress=rec, explain=False)  # the reading loop
    total = rec.calls[-1][1]
    assert total == pytest.approx(4.99, abs=0.02)
    rec.check(total=total)
    assert rec.calls[-1][0] == pytest.approx(total)
    rec = Recorder()
    build_report(str(out), progress=rec)
    assert rec.calls and rec.calls[-1][0] > 4.0


def test_ingest_calls_back_in_bytes(tmp_path):
    from imufdi_cli.pipeline import ingest_file, simulate_file

    capture = tmp_path / "c.bin"
    simulate_file(
        "paper-table4", str(tmp_path / "s.mcap"), seed=0, options={}, capture=str(capture)
    )
    rec = Recorder()
    ingest_file(str(capture), str(tmp_path / "c.mcap"), progress=rec)
    size = float(capture.stat().st_size)
    rec.check(total=size)
    assert rec.calls[-1][0] == pytest.approx(size, rel=0.05)
    assert np.all(np.diff([d for d, _ in rec.calls]) >= 0)
