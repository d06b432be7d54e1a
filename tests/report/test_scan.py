"""The streaming scan's bounded plot series."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from imufdi_cli.report import scan


def test_plot_series_keep_every_alarm_and_peak_when_decimating(monkeypatch):
    """Each kept row is its bucket's (``stride`` consecutive samples) row of the largest
    statistic (NaN lowest, first on ties) with the OR of the bucket's alarms, every bucket
    once, for any block sizes and after any number of halvings: a one-sample spike of the
    statistic and a one-sample alarm both reach the figure."""
    monkeypatch.setattr(scan, "PLOT_POINTS", 50)
    rng = np.random.default_rng(3)
    for _ in range(100):
        n = int(rng.integers(1, 2000))
        alarm = rng.random(n) < rng.choice([0.001, 0.01, 0.2])
        stat = rng.standard_normal(n).round(1)  # ties inside buckets
        stat[rng.random(n) < 0.05] = np.nan
        spike = int(rng.integers(n))
        stat[spike] = 1e6
        scores = rng.random((n, 3))
        t = np.arange(n) * 10
        series = scan._Series()
        pos = 0
        while pos < n:
            k = int(rng.integers(1, 300))
            rows = {"t_ns": t[pos : pos + k], "statistic": stat[pos : pos + k]}
            series.add({**rows, "alarm": alarm[pos : pos + k], "scores": scores[pos : pos + k]})
            pos += k
        kept = series.arrays()
        stride = series.stride
        assert kept["t_ns"].size == -(-n // stride) <= 2 * 50 + 300
        m = kept["t_ns"].size
        key = np.full(m * stride, -np.inf)  # buckets as rows, padded with the lowest key
        key[:n] = np.where(np.isnan(stat), -np.inf, stat)
        peak = np.arange(m) * stride + np.argmax(key.reshape(m, stride), axis=1)  # first
        np.testing.assert_array_equal(kept["t_ns"], t[peak])
        np.testing.assert_array_equal(kept["statistic"], stat[peak])
        np.testing.assert_array_equal(kept["scores"], scores[peak])
        padded = np.zeros(m * stride, bool)
        padded[:n] = alarm
        np.testing.assert_array_equal(kept["alarm"], padded.reshape(m, stride).any(axis=1))
        assert 1e6 in kept["statistic"]
    # without a statistic: the first row of each bucket (here 300 rows in blocks of 7: one
    # halving, stride 2 after 101 rows)
    series = scan._Series()
    for start in range(0, 300, 7):
        rows = np.arange(start, min(start + 7, 300))
        series.add({"t_ns": rows, "alarm": rows == 151})
    assert series.stride == 4
    kept = series.arrays()
    assert kept["t_ns"].tolist() == list(range(0, 300, 4))
    assert np.flatnonzero(kept["alarm"]).tolist() == [151 // 4]


# --- episodes: the same report from both encodings of the FdiEvent -----------------------

T0 = 10**12
GYROS = ["imu0.gyro.x", "imu1.gyro.x", "imu2.gyro.x"]
FAULTS = [
    {"id": "f0", "model": "step", "sensors": ["imu0.gyro.x"], "at_s": 2.0, "until_s": 4.0,
     "params": {"amp": 0.01}, "spec": "step:imu0.gyro.x,at=2s,until=4s,amp=0.01rad/s"},
    {"id": "f1", "model": "noise", "sensors": ["imu1.gyro.x"], "at_s": 6.0, "until_s": None,
     "params": {"factor": 3.0}, "spec": "noise:imu1.gyro.x,at=6s,factor=3"},
    {"id": "f2", "model": "step", "sensors": ["imu0.accel.x"], "at_s": 3.0, "until_s": None,
     "params": {"amp": 0.1}, "spec": "step:imu0.accel.x,at=3s,amp=0.1m/s^2"},
]  # fmt: skip


def _explanations(rng: np.random.Generator) -> list[dict]:
    """Episodes as detect writes them: 230 of glt on the gyros (more than are listed;
    some in the calibration window, some on no sensor or with no fit, intervals that
    cover the true size or not), a few of glt on the accelerometers (no status channel)
    and of bank (no detect record)."""
    from imufdi_cli.episodes import Episode, FaultFit

    out = []
    for k in range(250):
        detector, sensor_type, ids = "glt", "gyro", GYROS
        if k >= 230:
            detector = "bank" if k % 2 else "glt"
            sensor_type = "gyro" if k % 2 else "accel"
            ids = GYROS if k % 2 else ["imu0.accel.x", "imu1.accel.x"]
        start = T0 + int(rng.integers(0, 10**10))
        models = rng.choice(["step", "noise", "drift", "spikes", "stuck"], int(rng.integers(0, 3)))
        centre = rng.choice([0.01, 3.0, 0.1])
        fits = [
            FaultFit(str(m), float(centre), float(centre - rng.exponential(0.02)),
                     float(centre + rng.exponential(0.02)) if k % 9 else math.nan, 0, 1.0)
            for m in models
        ]  # fmt: skip
        sensors = [] if k % 17 == 3 else [str(rng.choice(ids))]
        out.append(
            Episode(
                detector=detector,
                sensor_type=sensor_type,
                start_ns=start,
                end_ns=start + int(rng.integers(0, 2 * 10**9)),
                decided_start_ns=start + 1000,
                decided_end_ns=start + 2 * 10**9 + 1000,
                alarms=int(rng.integers(1, 500)),
                sensors=sensors,
                peak_ratio=float(rng.exponential(5.0)),
                fits=fits,
            ).to_dict()
        )
    return sorted(out, key=lambda e: e["decided_end_ns"])


def _annotated_log(path, episodes: list[dict], *, old_events: bool, truth: bool) -> None:
    """Status of glt on the gyros (10 s at 100 Hz, calibration window 1 s), the injected
    truth, and the episodes as FdiEvent messages of this version's schema or of the one
    before start_ns/end_ns (``old_events``)."""
    from imufdi_cli.detectors.base import DetectionBlock
    from imufdi_cli.mcapio import McapWriter, register_events_channel
    from imufdi_cli.mcapio.events import EVENTS_TOPIC, decode_events, encode_episode_events
    from imufdi_cli.mcapio.records import MessageBatch
    from imufdi_cli.mcapio.schemas import FDI_EVENT_SCHEMA, FDI_EVENT_SCHEMA_NAME
    from imufdi_cli.mcapio.status import encode_status, register_status_channel
    from tests.mcapio.test_events import _event_channel, old_fdi_event_schema, old_fdi_payload

    rng = np.random.default_rng(11)
    n = 1000
    t_ns = T0 + np.arange(n, dtype=np.int64) * 10_000_000
    alarm = rng.random(n) < 0.3
    block = DetectionBlock(
        statistic=rng.exponential(3.0, n),
        threshold=np.full(n, 6.0),
        alarm=alarm,
        isolated=np.where(alarm, rng.integers(0, 3, n), -1).astype(np.int32),
        amplitude=np.where(alarm, 0.01, np.nan),
        scores=rng.random((n, 3)),
    )
    batch = encode_episode_events(1, episodes)
    with McapWriter(path) as writer:
        if truth:
            record = {"format": "imufdi.faults/1", "seed": 0, "t0_ns": T0, "faults": FAULTS}
            writer.add_metadata("imufdi.faults", {"json": json.dumps(record)})
        record = {"detector": "glt", "calibration_window_ns": [T0, T0 + 10**9]}
        writer.add_metadata("imufdi.detect.glt", {"json": json.dumps(record)})
        status = register_status_channel(writer, "glt", "gyro", GYROS)
        if old_events:
            schema = writer.register_schema(
                FDI_EVENT_SCHEMA_NAME, "ros2msg", old_fdi_event_schema()
            )
            events = writer.register_channel(EVENTS_TOPIC, "cdr", schema)
        else:
            events = register_events_channel(writer)
        for part in range(4):  # the episodes interleaved with the status, in log time
            rows = slice(part * 250, (part + 1) * 250)
            writer.add_batch(encode_status(status, t_ns[rows], _rows(block, rows)))
            due = (batch.log_time >= t_ns[rows][0]) & (batch.log_time < t_ns[rows][-1])
            if part == 3:
                due = batch.log_time >= t_ns[rows][0]
            if part == 0:
                due |= batch.log_time < t_ns[0]
            sub = batch.select(due)
            payloads = [sub.payload(i) for i in range(len(sub))]
            if old_events:
                decoded = decode_events(sub, _event_channel(FDI_EVENT_SCHEMA))
                payloads = [old_fdi_payload(p, e) for p, e in zip(payloads, decoded)]
            writer.add_batch(MessageBatch.from_payloads(events, sub.log_time, payloads))


def _rows(block, rows: slice):
    from imufdi_cli.detectors.base import DetectionBlock

    return DetectionBlock(
        statistic=block.statistic[rows],
        threshold=block.threshold[rows],
        alarm=block.alarm[rows],
        isolated=block.isolated[rows],
        amplitude=block.amplitude[rows],
        scores=block.scores[rows],
    )


def _outputs(path, tmp_path, *options: str) -> dict[str, str]:
    from tests.cli.conftest import invoke

    out = {name: tmp_path / f"out.{name}" for name in ("json", "md", "csv", "episodes.csv")}
    result = invoke(
        ["report", path, "--json", out["json"], "--markdown", out["md"], "--csv", out["csv"],
         "--episodes-csv", out["episodes.csv"], *options]
    )  # fmt: skip
    assert result.code == 0, result.stderr
    texts = {name: p.read_text() for name, p in out.items()}
    texts["terminal"] = result.out
    return {k: v.replace(str(path), "LOG") for k, v in texts.items()}


@pytest.mark.parametrize("truth", [True, False])
def test_report_is_the_same_from_both_encodings_of_the_episodes(tmp_path, truth) -> None:
    """The episode events of this version (typed start_ns/end_ns, the JSON parsed only
    for the listed episodes) and of the one before (every JSON parsed) give byte-identical
    report outputs: terminal, JSON, Markdown, CSV and episodes CSV, whole and windowed."""
    episodes = _explanations(np.random.default_rng(7))
    (tmp_path / "new").mkdir()
    (tmp_path / "old").mkdir()
    new, old = tmp_path / "new" / "log.mcap", tmp_path / "old" / "log.mcap"
    _annotated_log(new, episodes, old_events=False, truth=truth)
    _annotated_log(old, episodes, old_events=True, truth=truth)
    for options in ((), ("--start", "2.5", "--end", "8")):
        a = _outputs(new, tmp_path / "new", *options)
        b = _outputs(old, tmp_path / "old", *options)
        assert a == b
        data = json.loads(a["json"])
        scores = data["episode_scores"]["glt.gyro"]
        assert 0 < len(data["episodes"]) <= 200 + 20
        if not options:
            assert scores["listed"] == 200 and scores["omitted"] > 0
        if options:  # --start/--end confine every episode, of every channel
            starts = [(e["start_ns"] - T0) * 1e-9 for e in data["episodes"]]
            assert starts and all(2.5 <= s < 8 for s in starts)
        if truth:
            kinds = {e["match"] for e in data["episodes"]}
            # the calibration window (0-1 s) is outside --start 2.5
            assert {"fault", "false"} | ({"calibration"} if not options else set()) <= kinds
            assert "calibration" not in kinds or not options, kinds
            assert scores["matched"] > 0 and scores["false"] > 0
