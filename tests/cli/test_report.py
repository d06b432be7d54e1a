"""imufdi report: tables and files, gates exit 0/1/2, no-truth logs."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from tests.cli.conftest import assert_one_line_error


def test_report_table_and_files(cli, tmp_path, detected_log):
    files = {k: tmp_path / f"r.{k}" for k in ("json", "md", "csv", "xml")}
    result = cli(
        [
            "report",
            detected_log,
            "--json",
            files["json"],
            "--markdown",
            files["md"],
            "--csv",
            files["csv"],
            "--junit",
            files["xml"],
        ]
    )
    assert result.code == 0, result.stderr
    assert "FAR %" in result.out and "glt" in result.out
    data = json.loads(files["json"].read_text())
    gyro = next(r for r in data["results"] if r["detector"] == "glt" and r["sensor_type"] == "gyro")
    assert 0.0 <= gyro["far"] <= 0.2 and 0.0 <= gyro["mar"] <= 0.6
    assert data["faults"][0]["spec"].startswith("step:imu0.gyro.x")
    assert "| glt | gyro |" in files["md"].read_text()
    assert files["csv"].read_text().startswith("detector,sensor_type")
    ET.fromstring(files["xml"].read_text())


def test_gates(cli, detected_log, tmp_path):
    ok = cli(["report", detected_log, "--fail-if", "glt.gyro.far > 0.5"])
    assert ok.code == 0, ok.stderr
    junit = tmp_path / "g.xml"
    bad = cli(["report", detected_log, "--fail-if", "glt.gyro.far >= 0", "--junit", junit])
    assert bad.code == 1
    assert "glt.gyro.far" in bad.stderr
    assert ET.fromstring(junit.read_text()).get("failures") == "1"


def test_gate_usage_errors(cli, detected_log):
    assert_one_line_error(
        cli(["report", detected_log, "--fail-if", "glt.gyro.far"]), 2, "not of the form"
    )
    assert_one_line_error(
        cli(["report", detected_log, "--fail-if", "nope.gyro.far > 1"]), 2, "unknown detector"
    )
    assert_one_line_error(
        cli(["report", detected_log, "--fail-if", "glt.gyro.speed > 1"]), 2, "unknown metric"
    )
    assert_one_line_error(
        cli(["report", detected_log, "--fail-if", "pca-parity.gyro.far > 1"]), 2, "no results"
    )


def test_no_truth(cli, tmp_path, table4_log):
    out = tmp_path / "d.mcap"
    # the metrics without truth, not episodes: no explanation
    assert cli(["detect", table4_log, "-d", "glt", "--no-explain", "-o", out]).code == 0
    result = cli(["report", out, "--json", "-"])
    assert result.code == 0
    data = json.loads(result.stdout)
    assert data["has_truth"] is False and data["results"][0]["far"] is None
    assert "need truth" in result.stderr  # note goes to stderr when stdout carries JSON


def test_report_without_detection_is_bad_input(cli, table4_log):
    assert_one_line_error(cli(["report", table4_log]), 3, "imufdi detect")


def test_match_far_and_roc(cli, tmp_path, detected_log):
    out, roc, md = tmp_path / "r.json", tmp_path / "roc.csv", tmp_path / "r.md"
    result = cli(
        ["report", detected_log, "--match-far", "5%", "--json", out, "--roc", roc, "--markdown", md]
    )
    assert result.code == 0, result.stderr
    assert "MAR@FAR %" in md.read_text()
    data = json.loads(out.read_text())
    assert data["match_far"] == 0.05
    gyro = next(r for r in data["results"] if r["detector"] == "glt" and r["sensor_type"] == "gyro")
    for key in ("mar_at_far", "fir_at_far", "detection_delay_at_far_s", "threshold_scale_at_far"):
        assert gyro[key] is not None, key
    assert 0.0 <= gyro["mar_at_far"] <= 1.0 and gyro["threshold_scale_at_far"] > 0
    lines = roc.read_text().splitlines()
    assert lines[0] == "detector,sensor_type,threshold_scale,far,mar,fir,detection_delay_s"
    rows = [line.split(",") for line in lines[1:] if line.startswith("glt,gyro,")]
    far = [float(r[3]) for r in rows]
    mar = [float(r[4]) for r in rows if r[4]]
    assert far == sorted(far, reverse=True) and mar == sorted(mar)  # monotone curve
    # the figures are those of the detector's own calibration window: FAR out of sample
    assert gyro["calibration_samples"] > 0 and gyro["far_calibration"] is not None


def test_match_far_usage_errors(cli, detected_log, tmp_path):
    for bad in ("0", "1", "0%", "100%", "150%", "-1%", "abc", "1%%", "nan"):
        result = cli(["report", detected_log, "--match-far", bad])
        assert_one_line_error(result, 2, "--match-far")
    # checked before the input is read
    result = cli(["report", str(tmp_path / "missing.mcap"), "--match-far", "2"])
    assert_one_line_error(result, 2, "--match-far")


@pytest.mark.draws  # run early, on one worker (tests/conftest.py)
def test_plot_and_roc_plot(cli, tmp_path, faulty_log):
    import pytest

    pytest.importorskip("matplotlib")
    # glt on the gyros only: the report figure has one row (detector, sensor type) instead
    # of two, each row about 0.6 s of CPU in matplotlib; the rows are drawn alike
    # (tests/test_plots.py draws one from a synthetic report)
    detected = tmp_path / "gyro.mcap"
    result = cli(["detect", faulty_log, "-d", "glt", "--param", "glt.types=gyro", "-o", detected])
    assert result.code == 0, result.stderr
    roc = tmp_path / "roc.csv"
    result = cli(["report", detected, "--roc", roc, "--plot", tmp_path / "p.png"])
    assert result.code == 0, result.stderr
    assert (tmp_path / "p.png").read_bytes()[:4] == b"\x89PNG"  # the report figure
    assert roc.exists() and (tmp_path / "roc.png").read_bytes()[:4] == b"\x89PNG"


def test_unsweepable_detector_is_a_note_not_a_crash(cli, tmp_path, faulty_log):
    import numpy as np

    from imufdi_cli.detectors.base import DetectionBlock
    from imufdi_cli.mcapio import McapSource, McapWriter, encode_status, register_status_channel

    # copy the truth of faulty_log and add a status channel whose threshold is infinite
    with McapSource(str(faulty_log)) as src:
        metadata = dict(src.metadata)
    path = tmp_path / "flat.mcap"
    t_ns = 1_700_000_000 * 10**9 + np.arange(500, dtype=np.int64) * 10_000_000
    with McapWriter(path) as writer:
        cid = register_status_channel(writer, "glt", "gyro", [f"imu{k}.gyro.x" for k in range(3)])
        writer.add_batch(encode_status(cid, t_ns, DetectionBlock.empty(500, 3)))
        for name, data in metadata.items():
            writer.add_metadata(name, data)
    result = cli(["report", path, "--match-far", "1%", "--json", "-"])
    assert result.code == 0, result.stderr
    data = json.loads(result.stdout)
    assert any("no sweepable statistic" in note for note in data["notes"]), data["notes"]
    assert data["results"][0]["mar_at_far"] is None


def test_report_streams_stdin_through_a_spool(detected_log):
    import io

    from imufdi_cli.report import build_report

    class Pipe(io.RawIOBase):
        """A non-seekable stream, like a shell pipe."""

        def __init__(self, data: bytes) -> None:
            self.inner = io.BytesIO(data)

        def readable(self) -> bool:
            return True

        def seekable(self) -> bool:
            return False

        def readinto(self, buffer) -> int:  # type: ignore[no-untyped-def]
            chunk = self.inner.read(len(buffer))
            buffer[: len(chunk)] = chunk
            return len(chunk)

    piped = build_report(io.BufferedReader(Pipe(detected_log.read_bytes())), match_far=0.05)
    direct = build_report(str(detected_log), match_far=0.05)
    assert [e.metrics.to_dict() for e in piped.entries] == [
        e.metrics.to_dict() for e in direct.entries
    ]


def test_episodes_are_explained_and_scored_against_the_truth(cli, tmp_path, detected_log):
    out = {k: tmp_path / f"e.{k}" for k in ("json", "md", "csv")}
    result = cli(
        [
            "report",
            detected_log,
            "--json",
            out["json"],
            "--markdown",
            out["md"],
            "--episodes-csv",
            out["csv"],
        ]
    )
    assert result.code == 0, result.stderr
    assert "alarm episodes" in result.out
    data = json.loads(out["json"].read_text())
    matched = [
        e
        for e in data["episodes"]
        if e["match"] == "fault" and e["detector"] == "glt" and e["sensor_type"] == "gyro"
    ]
    # the 0.9 deg/s step on imu0.gyro.x from 2.5 s to the end: one long episode explains it
    longest = max(matched, key=lambda e: e["alarms"])
    assert longest["sensors"][0] == "imu0.gyro.x" and longest["fault_class"] == "step"
    step = longest["fits"][0]
    assert step["size_name"] == "amp" and step["low"] < step["size"] < step["high"]
    assert abs(step["size"] - 0.9 * 3.141592653589793 / 180) < 0.1 * 0.9 * 3.14159 / 180
    scores = data["episode_scores"]["glt.gyro"]
    assert (
        scores["matched"] >= 1
        and scores["episodes"] == scores["matched"] + scores["false"] + scores["wrong_sensor"]
    )
    assert "## Alarm episodes" in out["md"].read_text()
    lines = out["csv"].read_text().splitlines()
    assert lines[0].startswith("detector,sensor_type,start_s") and len(lines) > 1


def test_episode_outputs_never_overwrite_the_input(cli, detected_log, tmp_path):
    for option in ("--episodes-csv", "--roc"):
        before = detected_log.read_bytes()
        result = cli(["report", detected_log, option, detected_log])
        assert_one_line_error(result, 2, option)
        assert detected_log.read_bytes() == before


def test_episodes_respect_start_and_end(cli, tmp_path, detected_log):
    window, whole = tmp_path / "w.csv", tmp_path / "all.csv"
    result = cli(
        ["report", detected_log, "--start", "3s", "--end", "4.5s", "--episodes-csv", window]
    )
    assert result.code == 0, result.stderr
    assert cli(["report", detected_log, "--episodes-csv", whole]).code == 0

    def starts(path):
        lines = path.read_text().splitlines()[1:]
        return [float(line.split(",")[2]) for line in lines]

    inside = starts(window)
    assert inside and all(3.0 <= s < 4.5 for s in inside)
    assert len(starts(whole)) > len(inside)


def test_plot_without_matplotlib_fails_before_any_work(cli, tmp_path, detected_log, monkeypatch):
    import sys

    for name in [m for m in sys.modules if m == "matplotlib" or m.startswith("matplotlib.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib -> ImportError
    out = tmp_path / "r.json"
    result = cli(["report", detected_log, "--json", out, "--plot", tmp_path / "p.png"])
    assert_one_line_error(result, 2, "--plot needs matplotlib")
    assert "pip install" in result.stderr
    assert not out.exists() and not (tmp_path / "p.png").exists()
    assert result.stdout == b""  # no table either: nothing was computed


@pytest.mark.slow
@pytest.mark.parametrize("seed", [5, 6])
def test_each_of_two_simultaneous_faults_gets_its_amplitude_in_the_files(cli, tmp_path, seed):
    """bank: two simultaneous gyro faults, each with its own amplitude in the
    written status (FdiStatus ``amplitudes``), read back by ``imufdi report``: the per-fault
    estimate (a step's median amplitude, a drift's slope) within 5 % of the injected size,
    and the episode of the strongest fault carries the detector's amplitude."""
    clean, faulty, detected = (tmp_path / f"{k}.mcap" for k in ("s", "f", "d"))
    report, table = tmp_path / "r.json", tmp_path / "r.md"
    steps = [
        ["simulate", "--preset", "quadrotor-marg", "--seed", seed, "-o", clean],
        [
            "inject",
            clean,
            "--seed",
            seed,
            "-o",
            faulty,
            *("--fault", "step:imu0.gyro.z,at=5s,amp=0.5rad/s"),
            *("--fault", "drift:imu0.gyro.x,at=5s,rate=0.1rad/s^2"),
        ],
        ["detect", faulty, "-d", "bank", "--calibrate", "0s:2s", "-o", detected],
        ["report", detected, "--json", report, "--markdown", table],
    ]
    for args in steps:
        result = cli([args[0], "-q", *args[1:]])
        assert result.code == 0, (args[0], result.stderr)
    data = json.loads(report.read_text())
    gyro = next(r for r in data["results"] if r["sensor_type"] == "gyro")
    figures = {f["fault_id"]: f["amplitudes"] for f in gyro["faults"]}
    assert [(a["sensor"], a["size_name"]) for a in figures["f0"]] == [("imu0.gyro.z", "amp")]
    assert [(a["sensor"], a["size_name"]) for a in figures["f1"]] == [("imu0.gyro.x", "rate")]
    for fault_id in ("f0", "f1"):
        assert figures[fault_id][0]["ratio"] == pytest.approx(1.0, abs=0.05), fault_id
    assert "imu0.gyro.z 28" in table.read_text()  # 0.5 rad/s = 28.6 deg/s
    episode = next(
        e for e in data["episodes"] if e.get("fault_id") == "f0" and e["sensor_type"] == "gyro"
    )
    assert episode["sensors"][0] == "imu0.gyro.z"
    assert episode["amplitude"] == pytest.approx(0.5, rel=0.05)


def test_a_fault_free_log_shows_what_its_alarms_cost_and_gates_on_the_bound(cli, tmp_path, table4_log):  # fmt: skip
    out = tmp_path / "d.mcap"
    assert cli(["detect", table4_log, "-d", "glt", "--no-explain", "-o", out]).code == 0
    result = cli(["report", out, "--json", tmp_path / "r.json"])
    assert result.code == 0, result.stderr
    for header in ("Alarm %", "Episodes/h", "upper 95 %", "MTBFA h", "Tested h"):
        assert header in result.out, header
    assert "undefined" not in next(line for line in result.out.splitlines() if "gyro" in line)
    gyro = next(r for r in json.loads((tmp_path / "r.json").read_text())["results"] if r["sensor_type"] == "gyro")  # fmt: skip
    # 3 s after the 2 s calibration window of a 5 s log, at 100 Hz
    assert gyro["fault_free_hours"] == pytest.approx(3.0 / 3600, rel=0.01)
    assert gyro["false_episodes"] >= 1
    assert gyro["false_episodes_per_hour"] == pytest.approx(gyro["false_episodes"] / gyro["fault_free_hours"])  # fmt: skip
    assert gyro["false_episodes_per_hour_upper95"] > gyro["false_episodes_per_hour"]
    gate = "glt.gyro.false_episodes_per_hour_upper95 > 2"
    failed = cli(["report", out, "--fail-if", gate])
    assert failed.code == 1 and "false_episodes_per_hour_upper95" in failed.stderr
    assert cli(["report", out, "--fail-if", "glt.gyro.false_episodes_per_hour_upper95 > 1e9"]).code == 0  # fmt: skip


def test_match_budget_reads_the_figures_at_the_matched_threshold(cli, tmp_path, detected_log):
    out, md, csv = tmp_path / "r.json", tmp_path / "r.md", tmp_path / "r.csv"
    # 10/s: the 0.5 s of fault-free gyro time tested (2 s to the 2.5 s onset) hold 5
    # false episodes at that rate
    result = cli(["report", detected_log, "--match-budget", "10/s", "--json", out, "--markdown", md, "--csv", csv])  # fmt: skip
    assert result.code == 0, result.stderr
    data = json.loads(out.read_text())
    assert data["match_budget"] == pytest.approx(36000.0)
    gyro = next(r for r in data["results"] if r["sensor_type"] == "gyro")
    assert gyro["target_budget_per_hour"] == pytest.approx(36000.0)
    assert gyro["threshold_scale_at_budget"] > 0
    assert 0.0 <= gyro["mar_at_budget"] <= 1.0 and gyro["detection_delay_s_at_budget"] is not None
    assert "MAR@budget %" in md.read_text() and "mar_at_budget" in csv.read_text().splitlines()[0]
    short = cli(["report", detected_log, "--match-budget", "1/h", "--json", out])
    assert short.code == 0 and "too short to match 1/h" in short.out  # notes with the table
    assert json.loads(out.read_text())["results"][0]["mar_at_budget"] is None


def test_match_budget_usage_errors(cli, detected_log, tmp_path):
    for bad in ("0/h", "-1/h", "abc", "1/x", "inf"):
        assert_one_line_error(cli(["report", detected_log, "--match-budget", bad]), 2, "--match-budget")  # fmt: skip


def test_runs_under_a_budget_get_the_optimal_tests_reference_delay(cli, tmp_path, faulty_log):
    detected, out, md = tmp_path / "d.mcap", tmp_path / "r.json", tmp_path / "r.md"
    args = ["detect", faulty_log, "-d", "glt", "--false-alarms", "1/h", "--no-explain", "-o", detected]  # fmt: skip
    assert cli(args).code == 0
    assert cli(["report", detected, "--json", out, "--markdown", md]).code == 0
    gyro = next(r for r in json.loads(out.read_text())["results"] if r["sensor_type"] == "gyro")
    fault = gyro["faults"][0]
    # Lorden: ln(gamma K) / I samples for the 0.9 deg/s step on imu0.gyro.x, I the step's
    # information per sample in the evidence's noise (delta its sensitivity, z units per
    # rad/s in the detector's record, times the step; the outliers the detector measured
    # on its calibration), gamma the samples between false alarms at 1/h, K the bank's
    # hypotheses
    from imufdi_cli.maths.sequential import lorden_delay_samples
    from imufdi_cli.mcapio import McapSource

    with McapSource(str(detected)) as source:
        record = json.loads(source.metadata["imufdi.detect.glt"]["json"])
    budget = record["detector_metadata"]["types"]["gyro"]["budget"]
    delta = budget["sensitivity"][0] * np.deg2rad(0.9)
    outliers = budget["outlier_share"], budget["outlier_size"]
    want = lorden_delay_samples(delta**2, 100.0 * 3600, budget["hypotheses"], *outliers) / 100.0
    # paper-table4's gyro outliers (0.1 % of 1 deg/s) are in the calibration window: the
    # reference is longer than the Gaussian one
    assert outliers[0] > 0 and outliers[1] > 4.5
    assert want > lorden_delay_samples(delta**2, 100.0 * 3600, budget["hypotheses"]) / 100.0
    # 1e-11: the JSON's floats carry 12 significant digits (jsonout.SIGNIFICANT_DIGITS)
    assert fault["reference_delay_s"] == pytest.approx(want, rel=1e-11)
    assert fault["delay_ratio"] == pytest.approx(fault["detection_delay_s"] / want, rel=1e-11)
    assert gyro["reference_delay_s"] == fault["reference_delay_s"]
    assert gyro["delay_ratio"] == fault["delay_ratio"]
    assert "Reference delay s" in md.read_text()
