"""Gaps and dropouts are first-class: tested time excludes gaps (no rate changes with a
gap), an IMU that stops or slows is reported and the others go on being tested (a fault
on them is detected, the reduced redundancy raises no alarm), and report --start/--end
confines every episode."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tests.cli.conftest import assert_one_line_error

HOUR_NS = 3600 * 10**9


def _shift_after(source: Path, target: Path, after_s: float, shift_ns: int) -> None:
    """``source`` with every sample from ``after_s`` on moved ``shift_ns`` later (a gap)."""
    from imufdi_cli.log import ImuBlock
    from imufdi_cli.mcapio import read_array, write_array

    array, block = read_array(source)
    t = block.t_ns.copy()
    t[t - t[0] >= int(after_s * 1e9)] += shift_ns
    write_array(target, array, ImuBlock(t_ns=t, gyro=block.gyro, accel=block.accel))


def _drop(source: Path, target: Path, topic: str, after_s: float, until_s=None, every=None):
    """``source`` without ``topic``'s messages from ``after_s`` (to ``until_s``); with
    ``every``, one message in ``every`` is kept (a topic at a fraction of the rate)."""
    from imufdi_cli.mcapio import McapSource, McapWriter

    with McapSource(source) as src, McapWriter(target) as out:
        out.copy_channels(src.channels)
        for name, values in src.metadata.items():
            out.add_metadata(name, values)
        (cid,) = [c.id for c in src.channels.values() if c.topic == topic]
        t0 = None
        for batch in src.batches():
            t0 = int(batch.log_time.min()) if t0 is None else t0
            rel = (batch.log_time - t0) / 1e9
            drop = (batch.channel_id == cid) & (rel >= after_s)
            if until_s is not None:
                drop &= rel < until_s
            if every:
                mine = np.flatnonzero(batch.channel_id == cid)
                drop[mine[::every]] = False
            out.add_batch(batch.select(~drop))


@pytest.fixture(scope="module")
def logs(tmp_path_factory) -> Path:
    """A 6-IMU 12 s log, copies with imu2 stopping at 6 s and at half rate, each with a
    0.9 deg/s step on imu0.gyro.x at 9 s (inside the dropout)."""
    from tests.cli.conftest import invoke

    base = tmp_path_factory.mktemp("dropouts")
    made = invoke(
        ["simulate", "--imus", "6", "--duration", "12s", "--seed", "5", "-o", base / "full.mcap"]
    )
    assert made.code == 0, made.stderr
    _drop(base / "full.mcap", base / "stop.mcap", "/imu2/data_raw", 6.0)
    _drop(base / "full.mcap", base / "half.mcap", "/imu2/data_raw", 0.0, every=2)
    for name in ("full", "stop", "half"):
        done = invoke(
            [
                "inject",
                base / f"{name}.mcap",
                "--fault",
                "step:imu0.gyro.x,at=9s,amp=0.9deg/s",
                "-o",
                base / f"{name}-f.mcap",
            ]
        )
        assert done.code == 0, done.stderr
    return base


def _detect_report(cli, log: Path, out: Path, *extra: str) -> tuple[dict, dict, str]:
    detected = cli(
        [
            "detect",
            log,
            "-d",
            "glt",
            "--no-explain",
            "-o",
            out,
            "--json",
            out.with_suffix(".d.json"),
        ]
    )
    assert detected.code == 0, detected.stderr
    report = cli(["report", out, "--json", out.with_suffix(".r.json"), *extra])
    assert report.code == 0, report.stderr
    return (
        json.loads(out.with_suffix(".d.json").read_text()),
        json.loads(out.with_suffix(".r.json").read_text()),
        detected.stderr,
    )


def _entry(report: dict, sensor_type: str) -> dict:
    (entry,) = [e for e in report["results"] if e["sensor_type"] == sensor_type]
    return entry


@pytest.mark.parametrize("kind", ["stop", "half"])
def test_an_imu_that_stops_or_slows_is_reported_and_the_others_tested(cli, logs, tmp_path, kind):
    full_d, full_r, _ = _detect_report(cli, logs / "full-f.mcap", tmp_path / "full.mcap")
    drop_d, drop_r, stderr = _detect_report(cli, logs / f"{kind}-f.mcap", tmp_path / "drop.mcap")
    # every sample tested, none dropped
    assert drop_d["samples"] == full_d["samples"] == 1200
    warning = [w for w in drop_d["warnings"] if w.startswith("/imu2/data_raw has no sample")]
    assert len(warning) == 1, drop_d["warnings"]
    assert (
        "600 of 1200" in warning[0] and "between 6 s and 11.99 s" in warning[0]
        if kind == "stop"
        else "600 of 1200" in warning[0] or "599 of 1200" in warning[0]
    )
    assert f"warning: {warning[0]}" in stderr
    for sensor_type in ("gyro", "accel"):
        assert drop_d["validity"][sensor_type]["missing"] in (599, 600)
        assert drop_d["validity"][sensor_type]["invalid"] == 0
    gyro_full, gyro_drop = _entry(full_r, "gyro"), _entry(drop_r, "gyro")
    # the fault on imu0 during the dropout is detected
    (fault,) = gyro_drop["faults"]
    assert fault["detected"] and fault["faulty_samples"] == 300
    # the reduced redundancy makes no alarm: with the missing sensors replaced by the
    # others' consensus, glt's parity residual of a sample is never larger (same
    # calibration: the IMU stops after the window); at half rate the calibration keeps
    # the window's complete samples, half of them: its noise estimates differ, so the
    # false alarm rate may move by the sampling error of a 1 % test (one alpha)
    for sensor_type in ("gyro", "accel"):
        drop, full = _entry(drop_r, sensor_type), _entry(full_r, sensor_type)
        if kind == "stop":
            assert drop["false_alarms"] <= full["false_alarms"]
        else:
            assert drop["false_alarms"] / drop["fault_free_samples"] <= full["far"] + 0.01
    assert gyro_drop["samples"] == gyro_full["samples"]
    assert any("tested with an IMU missing" in n for n in drop_r["notes"])


def test_info_counts_partial_samples_and_names_the_imu(cli, logs):
    result = cli(["info", logs / "stop.mcap", "--json", "-"])
    assert result.code == 0, result.stderr
    info = json.loads(result.out)
    assert info["n_samples"] == 1200
    assert info["alignment"]["partial"] == 600 and info["alignment"]["dropped"] == 0
    assert any(w.startswith("/imu2/data_raw has no sample in 600") for w in info["warnings"])


def test_a_calibration_window_without_an_imu_is_refused_or_trimmed(cli, logs, tmp_path):
    short = tmp_path / "cal-short.mcap"
    _drop(logs / "full.mcap", short, "/imu2/data_raw", 0.5, until_s=1.0)
    result = cli(["detect", short, "-d", "glt", "--no-explain", "-o", tmp_path / "a.mcap"])
    assert result.code == 0, result.stderr
    assert "calibrated on the 150 complete ones" in result.stderr
    long = tmp_path / "cal-long.mcap"
    _drop(logs / "full.mcap", long, "/imu2/data_raw", 0.0, until_s=1.5)
    result = cli(["detect", long, "-d", "glt", "-o", tmp_path / "b.mcap"])
    assert_one_line_error(result, 3, "calibration window 0s:2s has an IMU missing in 150 of")
    assert not (tmp_path / "b.mcap").exists()


# --- gaps: tested time -----------------------------------------------------------------


def test_a_three_hour_gap_changes_no_rate_and_no_gate(cli, logs, tmp_path):
    """Alarm events and episodes per hour are per tested, fault-free hour: a 3-hour gap in
    a 12 s log (nothing tested there) leaves them as they are, and so the gate."""
    gap = tmp_path / "gap.mcap"
    _shift_after(logs / "full.mcap", gap, 4.0, 3 * HOUR_NS)
    injected = tmp_path / "gap-f.mcap"
    fault_at = 9 + 3 * 3600  # the same sample as the step at 9 s of the log without the gap
    made = cli(
        ["inject", gap, "--fault", f"step:imu0.gyro.x,at={fault_at}s,amp=0.9deg/s", "-o", injected]
    )
    assert made.code == 0, made.stderr
    runs = {}
    for name, log in (("full", logs / "full-f.mcap"), ("gap", injected)):
        out = tmp_path / f"{name}-d.mcap"
        # alpha 5 %: false alarms to count in a short log
        assert cli(["detect", log, "-d", "glt", "--param", "glt.alpha=0.05", "-o", out]).code == 0
        report = cli(["report", out, "--json", tmp_path / f"{name}.json"])
        assert report.code == 0, report.stderr
        runs[name] = json.loads((tmp_path / f"{name}.json").read_text())
    for sensor_type in ("gyro", "accel"):
        full, gap_entry = _entry(runs["full"], sensor_type), _entry(runs["gap"], sensor_type)
        assert gap_entry["false_alarms"] == full["false_alarms"]  # the same tests
        assert full["false_alarm_events_per_hour"] > 200
        # the same events over the same tested time: equal to rounding
        assert gap_entry["false_alarm_events_per_hour"] == pytest.approx(
            full["false_alarm_events_per_hour"], rel=1e-12
        )
        assert gap_entry["fault_free_hours"] == pytest.approx(full["fault_free_hours"], rel=1e-12)
        assert gap_entry["duration_s"] > 3 * 3600  # the span still shows the gap
        score_full = runs["full"]["episode_scores"][f"glt.{sensor_type}"]
        score_gap = runs["gap"]["episode_scores"][f"glt.{sensor_type}"]
        assert score_gap["false_episodes_per_hour"] == pytest.approx(
            score_full["false_episodes_per_hour"], rel=1e-12
        )
    # one denominator: alarm events and episodes per hour divide by the same hours
    entry = _entry(runs["full"], "accel")
    assert entry["fault_free_hours"] == pytest.approx(entry["fault_free_samples"] * 0.01 / 3600)
    gate = ["--fail-if", "glt.accel.false_alarm_events_per_hour > 200"]
    for name in ("full", "gap"):
        result = cli(["report", tmp_path / f"{name}-d.mcap", *gate])
        assert result.code == 1, (name, result.stderr)


# --- report --start/--end and episodes -------------------------------------------------


def test_report_start_end_confines_every_episode(cli, logs, tmp_path):
    """variance-drop episodes (no status channel of their own) are windowed like the
    others, and so are those of every channel: none starts outside --start/--end."""
    stuck = tmp_path / "stuck.mcap"
    made = cli(
        ["inject", logs / "full.mcap", "--fault", "stuck:imu3.gyro.z,at=3s,until=5s", "-o", stuck]
    )
    assert made.code == 0, made.stderr
    out = tmp_path / "stuck-d.mcap"
    assert cli(["detect", stuck, "-d", "glt", "-o", out]).code == 0
    whole = json.loads(cli(["report", out, "--json", "-"]).out)
    drops = [e for e in whole["episodes"] if e["detector"] == "variance-drop"]
    assert drops, "the stuck output should raise a variance-drop episode"
    t0 = min(e["start_ns"] for e in whole["episodes"]) - 10**10  # before any episode
    for start, end in ((7.0, 10.0), (1.0, 2.5)):
        windowed = json.loads(
            cli(["report", out, "--start", f"{start}s", "--end", f"{end}s", "--json", "-"]).out
        )
        record_t0 = _log_start(out)
        for episode in windowed["episodes"]:
            rel = (episode["start_ns"] - record_t0) * 1e-9
            assert start <= rel < end, episode
        assert t0 < record_t0
    windowed = json.loads(cli(["report", out, "--start", "7s", "--json", "-"]).out)
    assert "variance-drop.gyro" not in windowed["episode_scores"]
    assert whole["episode_scores"]["variance-drop.gyro"]["false_episodes_per_hour"] is not None


def _log_start(log: Path) -> int:
    from imufdi_cli.mcapio import McapSource

    with McapSource(log) as src:
        return int(json.loads(src.metadata["imufdi.detect.glt"]["json"])["t0_ns"])
