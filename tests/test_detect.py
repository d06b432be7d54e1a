"""detect: decision times, look-ahead and the recorded calibration window."""

from __future__ import annotations

import json
from typing import Any, ClassVar

import numpy as np
import pytest
from numpy.testing import assert_array_equal

from imufdi_cli.detect import calibration_window_ns, decision_positions, detect_file
from imufdi_cli.detectors import DETECTORS
from imufdi_cli.detectors.base import DetectionBlock, DetectorBase
from imufdi_cli.errors import CalibrationError
from imufdi_cli.mcapio import McapSource, read_status


def test_decision_positions():
    # rows 10..14 returned after 20 samples were passed in
    assert decision_positions(10, 5, 20, 0).tolist() == [10, 11, 12, 13, 14]
    assert decision_positions(10, 5, 20, 7).tolist() == [17, 18, 19, 19, 19]
    assert decision_positions(10, 5, 20, None).tolist() == [19] * 5  # undeclared: newest
    assert decision_positions(0, 0, 0, 3).size == 0


def test_calibration_window_ns():
    assert calibration_window_ns(None, 0, 0.0, 2.0) is None
    assert calibration_window_ns(10**9, 5 * 10**9, 0.5, 2.0) == [15 * 10**8, 3 * 10**9]
    assert calibration_window_ns(10**9, 5 * 10**9, 0.0, None) == [10**9, 5 * 10**9 + 1]


class HoldBack(DetectorBase):
    """Test detector: holds every sample back ``lookahead_samples`` samples; statistic =
    sample index, so rows can be matched to samples."""

    name: ClassVar[str] = "hold3"
    PARAMS: ClassVar[dict[str, Any]] = {}
    lookahead_samples = 3

    def __init__(self) -> None:
        self.seen = 0
        self.held = 0

    def fit(self, calibration: Any, array: Any) -> None:
        self.n = array.n_sensors("gyro")

    def _rows(self, count: int) -> dict[str, DetectionBlock]:
        block = DetectionBlock.empty(count, self.n)
        block.statistic = np.arange(
            self.seen - self.held, self.seen - self.held + count, dtype=float
        )
        block.threshold = np.full(count, 1e9)
        self.held -= count
        return {"gyro": block}

    def process(self, block: Any) -> dict[str, DetectionBlock]:
        self.seen += len(block)
        self.held += len(block)
        return self._rows(max(self.held - self.lookahead_samples, 0))

    def flush(self) -> dict[str, DetectionBlock]:
        return self._rows(self.held)

    def metadata(self) -> dict[str, Any]:
        return {}


@pytest.fixture(scope="module")
def sim_log(tmp_path_factory):
    from imufdi_cli.mcapio import write_array
    from imufdi_cli.simulate import config_from_options, simulate_block

    path = tmp_path_factory.mktemp("d") / "s.mcap"
    array, block = simulate_block(config_from_options("paper-table4", seed=3, duration="3s"))
    write_array(str(path), array, block)
    return path


def test_rows_carry_decision_times(sim_log, tmp_path, monkeypatch):
    monkeypatch.setitem(DETECTORS, "hold3", "tests.test_detect:HoldBack")
    out = tmp_path / "d.mcap"
    # rows and the detector record, not episodes: no explanation (the same rows:
    # test_no_explain_writes_the_same_status_and_alarms_without_episodes)
    detectors = [("glt", {}), ("hold3", {})]
    detect_file(str(sim_log), str(out), detectors, calibrate=(0.0, 1.0), explain=False)
    status = read_status(str(out))
    glt = status[("glt", "gyro")]
    assert glt.has_decided
    assert_array_equal(glt.decided_ns, glt.t_ns)  # causal: the sample time
    held = status[("hold3", "gyro")]
    n = len(held)
    assert_array_equal(held.statistic, np.arange(n))  # one row per sample, in order
    later = np.minimum(np.arange(n) + 3, n - 1)
    assert_array_equal(held.decided_ns, held.t_ns[later])
    with McapSource(str(out)) as src:
        record = json.loads(src.metadata["imufdi.detect.glt"]["json"])
    t0 = int(glt.t_ns[0])
    assert record["calibration_window_ns"] == [t0, t0 + 10**9]
    assert record["lookahead_samples"] == 0
    inside = (glt.t_ns >= t0) & (glt.t_ns < t0 + 10**9)
    assert record["calibration_samples"] == int(np.count_nonzero(inside))


def _chunk_contents(path) -> list[bytes]:
    """Contents of the Chunk records of an MCAP file, in file order."""
    import struct

    raw = path.read_bytes()
    out = []
    position = 8
    while position + 9 <= len(raw):
        opcode, length = struct.unpack_from("<BQ", raw, position)
        if opcode == 0x06:
            out.append(raw[position + 9 : position + 9 + length])
        if opcode == 0x0F:
            break
        position += 9 + length
    return out


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_whole_input_chunks_are_copied_verbatim(tmp_path, compression):
    """Input chunks of exactly one batch are written as they are (no recompression); the
    others, and the new channels, go through the writer; every message is kept."""
    from mcap.reader import make_reader

    from imufdi_cli.mcapio import ImuArrayWriter, McapWriter
    from imufdi_cli.simulate import config_from_options, simulate_block

    path = tmp_path / "in.mcap"
    array, block = simulate_block(config_from_options("paper-table4", seed=5, duration="2s"))
    with McapWriter(str(path), compression=compression, chunk_size=1 << 18) as writer:
        ImuArrayWriter(writer, array).write_block(block)
    out = tmp_path / "out.mcap"
    detect_file(str(path), str(out), [("glt", {})], compression=compression, explain=False)
    before = _chunk_contents(path)
    after = set(_chunk_contents(out))
    copied = [c for c in before if c in after]
    # 2 s of 16 IMUs: 3,200 messages of 355 bytes in ~256 KiB chunks; all but the last
    # (short) one are whole batches
    assert len(before) >= 4
    assert len(copied) >= len(before) - 1

    def messages(p):
        # in file order: the list is sorted here (the reader's log-time merge of the chunks
        # was half of this test's CPU)
        with open(p, "rb") as stream:
            reader = make_reader(stream, validate_crcs=True)
            return sorted(
                (c.topic, m.log_time, m.sequence, m.data)
                for _, c, m in reader.iter_messages(log_time_order=False)
            )

    ours = messages(out)
    assert [m for m in ours if not m[0].startswith("/imufdi")] == messages(path)
    with McapSource(out) as src:
        counts = src.summary_channel_counts
        assert counts is not None and sum(counts.values()) == len(ours)
        assert sum(len(b) for b in src.batches()) == len(ours)
        assert not src.warnings


def test_recompressed_when_the_compression_differs(tmp_path):
    from imufdi_cli.mcapio import write_array
    from imufdi_cli.simulate import config_from_options, simulate_block

    path = tmp_path / "in.mcap"
    array, block = simulate_block(config_from_options("paper-table4", seed=5, duration="4s"))
    write_array(str(path), array, block, compression="zstd")
    out = tmp_path / "out.mcap"
    detect_file(str(path), str(out), [("glt", {})], compression="lz4", explain=False)
    assert not set(_chunk_contents(path)) & set(_chunk_contents(out))
    assert all(b"lz4" in c[:40] for c in _chunk_contents(out))


def test_no_explain_writes_the_same_status_and_alarms_without_episodes(sim_log, tmp_path):
    """--no-explain: the same status channels and alarm events, no episode events, and the
    episodes package is not even imported."""
    import subprocess
    import sys

    from imufdi_cli.mcapio.events import EVENTS_TOPIC, read_events

    explained, plain = tmp_path / "e.mcap", tmp_path / "p.mcap"
    detect_file(str(sim_log), str(explained), [("glt", {})])
    code = (
        "import sys\n"
        "from imufdi_cli.detect import detect_file\n"
        f"detect_file({str(sim_log)!r}, {str(plain)!r}, [('glt', {{}})], explain=False)\n"
        "print(sorted(m for m in ('imufdi_cli.episodes',) if m in sys.modules))\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "[]"
    status = {p: read_status(str(p), "glt") for p in (explained, plain)}
    assert set(status[explained]) == set(status[plain]) == {("glt", "gyro"), ("glt", "accel")}
    for key, a in status[explained].items():
        b = status[plain][key]
        assert_array_equal(a.statistic, b.statistic)
        assert_array_equal(a.alarm, b.alarm)
        assert_array_equal(a.isolated, b.isolated)
    events = {p: read_events(str(p), EVENTS_TOPIC) for p in (explained, plain)}
    kinds = {p: [e["event"] for _, e in ev] for p, ev in events.items()}
    assert "episode" in kinds[explained]  # glt alarms on this log: episodes are explained
    assert "episode" not in kinds[plain]
    alarms = {p: [(t, e) for t, e in ev if e["event"] != "episode"] for p, ev in events.items()}
    assert alarms[explained] == alarms[plain]


def test_read_ahead_gives_the_same_output_and_its_thread_ends(sim_log, tmp_path):
    """detect may decompress the input's large chunks on a worker thread (read_ahead; off
    by default, as the reader's): the same file as without and as the default, and the
    thread is shut down when detect returns, or when it fails."""
    import threading

    outputs = []
    for read_ahead in (False, True, None):
        out = tmp_path / f"{read_ahead}.mcap"
        detect_file(str(sim_log), str(out), [("glt", {})], explain=False, read_ahead=read_ahead)
        outputs.append(out.read_bytes())
    assert outputs[0] == outputs[1] == outputs[2]
    with pytest.raises(CalibrationError):
        detect_file(
            str(sim_log),
            str(tmp_path / "x.mcap"),
            [("glt", {})],
            calibrate=(50.0, 60.0),
            read_ahead=True,
        )
    for thread in threading.enumerate():
        if thread.name.startswith("imufdi-chunks"):
            thread.join(5)
    assert not [t for t in threading.enumerate() if t.name.startswith("imufdi-chunks")]
    assert not (tmp_path / "x.mcap").exists()


def test_a_channel_far_above_its_level_says_so() -> None:
    from types import SimpleNamespace

    from imufdi_cli.detect import TypeSummary, level_warning, observed_level_warnings

    per_sample = SimpleNamespace(name="glt", alpha=0.01, false_alarms=0.0, persistence=1)
    # 57 alpha in motion (glt window=10 on conical6) and a quiet channel
    noisy = {"gyro": TypeSummary(samples=10000, alarms=5700), "accel": TypeSummary(10000, 90)}
    notes = observed_level_warnings(per_sample, noisy, 100.0)
    assert len(notes) == 1 and "glt.gyro" in notes[0] and "57 times its level" in notes[0]
    assert "3,600 false alarm episodes an hour" in (level_warning(per_sample, 100.0) or "")
    budgeted = SimpleNamespace(name="glt", alpha=0.01, false_alarms=1 / 3600, persistence=1)
    assert level_warning(budgeted, 100.0) is None
    # 6 episodes in 10 min at 1/h is 36/h: over 10 x the budget; 4 episodes are too few to say
    six = {"gyro": TypeSummary(samples=60000, events=6)}
    assert "6 alarm episodes" in observed_level_warnings(budgeted, six, 100.0)[0]
    assert not observed_level_warnings(budgeted, {"gyro": TypeSummary(60000, events=4)}, 100.0)


def test_detect_warns_when_a_test_loses_its_level_in_motion(tmp_path) -> None:
    from imufdi_cli.detect import detect_file
    from imufdi_cli.pipeline import simulate_file

    log = tmp_path / "c6.mcap"
    simulate_file("conical6", str(log), seed=5, options={"duration": "30s"})
    moving = detect_file(str(log), str(tmp_path / "a.mcap"), [("glt", {"window": "10"})])
    assert any("times its level" in w and "glt.gyro" in w for w in moving.warnings)
    budget = detect_file(str(log), str(tmp_path / "b.mcap"), [("glt", {})], false_alarms=1 / 3600)
    assert not any("times its level" in w or "against a budget" in w for w in budget.warnings)


def test_one_sample_episodes_of_a_per_sample_test_are_explained_by_their_sample(
    sim_log, tmp_path, monkeypatch
):
    """Per sample (glt at alpha), an episode of one alarm is explained by its sample alone
    (``explained_by: sample``: ``none``, or ``spikes`` for paper-table4's gyro outliers);
    longer ones by the fits; under a false-alarm budget every episode is fitted."""
    from imufdi_cli.mcapio.events import EVENTS_TOPIC, read_events

    out = tmp_path / "e.mcap"
    detect_file(str(sim_log), str(out), [("glt", {"alpha": 0.05})])
    episodes = [
        e["episode"] for _, e in read_events(str(out), EVENTS_TOPIC) if e["event"] == "episode"
    ]
    paths = {(e["alarms"] == 1 and e["fragments"] == 1, e["explained_by"]) for e in episodes}
    assert (True, "sample") in paths and (False, "fits") in paths
    assert paths <= {(True, "sample"), (False, "fits")}
    assert {e["fault_class"] for e in episodes if e["explained_by"] == "sample"} <= {
        "none",
        "spikes",
    }
    from imufdi_cli.episodes import EpisodeBuilder

    chosen = []
    real = EpisodeBuilder.for_detector

    def spy(self, detector, **options):
        chosen.append(options.get("sample_explanations"))
        return real(self, detector, **options)

    monkeypatch.setattr(EpisodeBuilder, "for_detector", spy)
    detect_file(str(sim_log), str(tmp_path / "b.mcap"), [("glt", {})], false_alarms=1 / 3600)
    detect_file(str(sim_log), str(tmp_path / "p.mcap"), [("glt", {})])
    assert chosen == [False, False, True, True]  # (gyro and accel builders of each run)


@pytest.mark.parametrize(
    "options",
    [["--no-explain"], ["--no-explain", "--false-alarms", "1/h"], [], ["--false-alarms", "1/h"]],
    ids=["per-sample", "budget", "per-sample-explained", "budget-explained"],
)
def test_glt_imports_no_scipy(tmp_path, fresh_python, options):
    """``detect -d glt`` (per-sample and under a budget, with and without explanations)
    imports no scipy module at all (about 0.27 s of CPU for scipy.special alone): its
    thresholds' and the episode intervals' chi-square, F and t quantiles are
    maths/incomplete.py's, and the noise calibration's non-negative least squares is the
    unconstrained solution on a white-noise calibration, without ``scipy.optimize``."""
    from pathlib import Path

    sample = Path(__file__).resolve().parents[1] / "imufdi_cli/sample_logs/paper-table4.mcap"
    argv = ["imufdi", "detect", "-d", "glt", *options, str(sample)]
    argv += ["-o", str(tmp_path / "out.mcap"), "-q"]
    probe = (
        "import runpy, sys\n"
        f"sys.argv = {argv!r}\n"
        "try:\n    runpy.run_module('imufdi_cli', run_name='__main__')\n"
        "except SystemExit as done:\n    assert done.code in (0, 1, None), done.code\n"
        "print(sorted(m for m in sys.modules if m == 'scipy' or m.startswith('scipy.')))\n"
    )
    done = fresh_python(probe)
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "out.mcap").exists()
    assert done.stdout.strip().splitlines()[-1] == "[]"
