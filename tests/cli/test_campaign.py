"""imufdi campaign: outputs, gates, bad specs (exit 2, nothing written), kill and resume."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from tests.cli.conftest import assert_one_line_error

SPEC = """
[campaign]
name = "cli"
seeds = [0, 1]
calibrate = "0s:0.6s"
metrics = ["far", "mar", "detection_probability"]

[[base]]
preset = "paper-table4"
options = { duration = "1s" }

[[fault]]
model = "step"
sensor = "imu0.gyro.x"
at = "0.7s"
amp = ["0.3deg/s", "1.5deg/s"]

[[detector]]
name = "glt"
"""

#: 24 runs of the full 5 s paper-table4 log: long enough to kill half-way.
RESUME_SPEC = """
[campaign]
name = "resume"
seeds = [0, 1, 2, 3, 4, 5]

[[base]]
preset = "paper-table4"

[[fault]]
model = "step"
sensor = ["imu0.gyro.x", "imu3.gyro.y"]
at = "2.5s"
amp = ["0.5deg/s", "0.9deg/s"]

[[detector]]
name = "glt"
"""


def write(tmp_path: Path, text: str, name: str = "spec.toml") -> Path:
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


def test_campaign_writes_results_and_gates(cli, tmp_path):
    spec = write(tmp_path, SPEC)
    out = tmp_path / "out"
    result = cli(["campaign", spec, "-o", out, "--jobs", "1", "--fail-if", "glt.gyro.far > 0.5"])
    assert result.code == 0, result.stderr
    assert "4 runs (4 executed, 0 resumed, 0 failed)" in result.stderr
    assert "gate passed" in result.stderr
    names = {p.name for p in out.iterdir()}
    assert {"runs", "runs.csv", "summary.json", "summary.md"} <= names
    summary = json.loads((out / "summary.json").read_text())
    assert [g["amplitude"] for g in summary["groups"]] == ["0.3deg/s", "1.5deg/s"]
    # existing results need --resume (exit 2, nothing run)
    assert_one_line_error(cli(["campaign", spec, "-o", out]), 2, "use --resume")
    failing = cli(
        [
            "campaign", spec, "-o", out, "--resume", "--json",
            "--fail-if", "glt.gyro.detection_probability < 1",
        ]
    )  # fmt: skip
    assert failing.code == 1, failing.stderr
    assert "0 executed, 4 resumed" in failing.stderr and "gate FAILED" in failing.stderr
    # --json: the summary (through the one JSON writer), also when a gate fails
    from imufdi_cli.jsonout import clean

    head = {"format_version": 1, "command": "campaign"}  # every --json object's first keys
    expected = {**head, **clean(json.loads((out / "summary.json").read_text()))}
    assert json.loads(failing.out) == expected


def test_campaign_on_base_log_files(cli, tmp_path):
    for seed in (1, 2):
        made = cli(
            [
                "simulate",
                "--preset",
                "paper-table4",
                "--duration",
                "1s",
                "--seed",
                str(seed),
                "-o",
                tmp_path / f"log{seed}.mcap",
            ]
        )
        assert made.code == 0, made.stderr
    text = SPEC.replace(
        'preset = "paper-table4"\noptions = { duration = "1s" }', 'files = "log*.mcap"'
    )
    result = cli(["campaign", write(tmp_path, text), "-o", tmp_path / "out", "--jobs", "1"])
    assert result.code == 0, result.stderr
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["failed"] == 0
    assert {g["base"] for g in summary["groups"]} == {"log1.mcap", "log2.mcap"}


BAD = {
    "detector": (SPEC.replace('name = "glt"', 'name = "zzz"'), "unknown detector 'zzz'"),
    "preset": (SPEC.replace('"paper-table4"', '"mars"'), "unknown preset 'mars'"),
    "metric": (SPEC.replace('"far", "mar"', '"far", "fun"'), "unknown metric 'fun'"),
    "empty": (SPEC[: SPEC.index("[[fault]]")] + '[[detector]]\nname = "glt"\n', "fault matrix"),
    "unreadable": (
        SPEC.replace(
            'preset = "paper-table4"\noptions = { duration = "1s" }', 'files = "bad.mcap"'
        ),
        "unreadable base log",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_spec_exits_2_and_writes_nothing(cli, tmp_path, case):
    text, fragment = BAD[case]
    (tmp_path / "bad.mcap").write_bytes(b"\x89MCAP0\r\n garbage")
    out = tmp_path / "out"
    result = cli(["campaign", write(tmp_path, text), "-o", out])
    assert_one_line_error(result, 2, fragment)
    assert not out.exists()


def test_bad_gate_and_scheduler_exit_2_before_any_run(cli, tmp_path):
    spec = write(tmp_path, SPEC)
    result = cli(["campaign", spec, "-o", tmp_path / "o", "--fail-if", "glt.gyro.far >> 1"])
    assert_one_line_error(result, 2, "--fail-if")
    assert not (tmp_path / "o").exists()
    result = cli(["campaign", spec, "-o", tmp_path / "o", "--scheduler", "ftp://x"])
    assert_one_line_error(result, 2, "tcp://HOST:PORT and local:N")
    assert not (tmp_path / "o").exists()


def children_of(pid: int) -> list[int]:
    found = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        found += [int(c) for c in (task / "children").read_text().split()]
    return found


def alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except FileNotFoundError:
        return False
    return state != "Z"


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_sigkill_half_way_then_resume_equals_uninterrupted(cli, tmp_path):
    spec = write(tmp_path, RESUME_SPEC)
    reference = cli(["campaign", spec, "-o", tmp_path / "ref", "--jobs", "2"])
    assert reference.code == 0, reference.stderr

    out = tmp_path / "killed"
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    command = [sys.executable, "-m", "imufdi_cli", "campaign", str(spec), "-o", str(out)]
    proc = subprocess.Popen(
        [*command, "--jobs", "2"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env=env,
        start_new_session=True,
    )
    workers: list[int] = []
    try:
        deadline = time.monotonic() + 60
        while len(list(out.glob("runs/*.json"))) < 4:
            assert proc.poll() is None, "campaign finished before it could be killed"
            assert time.monotonic() < deadline, "no run finished within 60 s"
            time.sleep(0.02)
        workers = children_of(proc.pid)
        assert len(workers) >= 2, workers  # the spawned pool (and its resource tracker)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
        # orphaned pool workers notice the dead parent and exit
        deadline = time.monotonic() + 10
        while any(alive(w) for w in workers) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not any(alive(w) for w in workers), "pool workers outlived the killed campaign"
    finally:
        for pid in [proc.pid, *workers]:
            if alive(pid):
                os.kill(pid, signal.SIGKILL)

    done = {p.name: (p.stat().st_ino, p.stat().st_mtime_ns) for p in out.glob("runs/*.json")}
    assert 4 <= len(done) < 24, len(done)
    assert not (out / "runs.csv").exists()
    resumed = cli(["campaign", spec, "-o", out, "--jobs", "2", "--resume"])
    assert resumed.code == 0, resumed.stderr
    assert f"24 runs ({24 - len(done)} executed, {len(done)} resumed, 0 failed)" in resumed.stderr
    after = {p.name: (p.stat().st_ino, p.stat().st_mtime_ns) for p in out.glob("runs/*.json")}
    assert len(after) == 24
    assert all(after[name] == stamp for name, stamp in done.items())  # no run executed twice
    assert (out / "runs.csv").read_text() == (tmp_path / "ref" / "runs.csv").read_text()
    ref_summary = json.loads((tmp_path / "ref" / "summary.json").read_text())
    new_summary = json.loads((out / "summary.json").read_text())
    assert new_summary["groups"] == ref_summary["groups"]


# --- malformed specs, results-directory lock, campaigns where every run fails ----------

MALFORMED = {
    "campaign not a table": ("campaign = 5\n", "campaign: expected a table [campaign], got int"),
    "options not a table": (
        SPEC.replace('options = { duration = "1s" }', 'options = "x"'),
        "base[0].options: expected a table",
    ),
    "deep nesting": (SPEC + "x = " + "[" * 5000 + "]" * 5000 + "\n", "nested too deeply"),
    "fault after the log": (
        SPEC.replace('at = "0.7s"', 'at = "100s"'),
        "at (100 s) is after the log ends (0.99 s)",
    ),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_specs_exit_2_naming_the_problem(cli, tmp_path, case):
    text, fragment = MALFORMED[case]
    out = tmp_path / "out"
    result = cli(["campaign", write(tmp_path, text), "-o", out])
    assert_one_line_error(result, 2, fragment)
    assert not out.exists()


def test_a_second_campaign_on_one_directory_is_refused_naming_the_holder(cli, tmp_path):
    from imufdi_cli.campaign import LOCK_NAME, results_lock

    spec = write(tmp_path, SPEC)
    out = tmp_path / "out"
    out.mkdir()
    with results_lock(out):  # as a running campaign holds it
        result = cli(["campaign", spec, "-o", out, "--jobs", "1", "--resume"])
    assert_one_line_error(result, 2, f"another campaign (pid {os.getpid()} on")
    assert not (out / "runs").exists()
    # a lock file left by a dead campaign does not block: the kernel released its lock
    (out / LOCK_NAME).write_text("999999999 elsewhere\n")
    result = cli(["campaign", spec, "-o", out, "--jobs", "1"])
    assert result.code == 0, result.stderr
    assert (out / LOCK_NAME).read_text().split()[0] == str(os.getpid())


@pytest.mark.slow
def test_a_lock_held_by_another_process_names_its_pid(cli, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time; from pathlib import Path; "
            "from imufdi_cli.campaign import results_lock\n"
            "with results_lock(Path(sys.argv[1])):\n"
            "    print('locked', flush=True); time.sleep(60)",
            str(out),
        ],
        stdout=subprocess.PIPE,
        text=True,
        env=dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2])),
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "locked"
        result = cli(["campaign", write(tmp_path, SPEC), "-o", out, "--jobs", "1"])
        assert_one_line_error(result, 2, f"another campaign (pid {holder.pid} on")
    finally:
        holder.kill()
        holder.wait()
    result = cli(["campaign", write(tmp_path, SPEC), "-o", out, "--jobs", "1"])
    assert result.code == 0, result.stderr


def test_all_runs_failing_on_their_data_exits_3(cli, tmp_path):
    spec = write(tmp_path, SPEC.replace('calibrate = "0s:0.6s"', 'calibrate = "5s:6s"'))
    out = tmp_path / "out"
    result = cli(["campaign", spec, "-o", out, "--jobs", "1"])
    assert_one_line_error(result, 3, "all 4 runs failed (first: run ")
    assert "4 runs (4 executed, 0 resumed, 4 failed)" in result.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["failed"] == 4 and summary["failures"][0]["error"]


def test_all_runs_failing_on_a_bug_exits_4(cli, tmp_path, monkeypatch):
    import imufdi_cli.campaign.run

    def bug(desc):
        raise ZeroDivisionError("division by zero")

    monkeypatch.setattr(imufdi_cli.campaign.run, "_execute", bug)
    result = cli(["campaign", write(tmp_path, SPEC), "-o", tmp_path / "out", "--jobs", "1"])
    assert_one_line_error(result, 4, "ZeroDivisionError: division by zero")


def test_some_runs_failing_still_exits_0(cli, tmp_path, monkeypatch):
    import imufdi_cli.campaign.run

    real = imufdi_cli.campaign.run._execute

    def flaky(desc):
        if desc["seed"] == 1:
            raise ZeroDivisionError("division by zero")
        return real(desc)

    monkeypatch.setattr(imufdi_cli.campaign.run, "_execute", flaky)
    result = cli(["campaign", write(tmp_path, SPEC), "-o", tmp_path / "out", "--jobs", "1"])
    assert result.code == 0, result.stderr
    assert "2 failed" in result.stderr


@pytest.mark.slow
def test_sigterm_stops_a_campaign_cleanly_and_resume_finishes_it(cli, tmp_path):
    spec = write(tmp_path, RESUME_SPEC)
    out = tmp_path / "out"
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    proc = subprocess.Popen(
        [sys.executable, "-m", "imufdi_cli", "campaign", str(spec), "-o", str(out), "--jobs", "1"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    deadline = time.monotonic() + 120
    while len(list(out.glob("runs/*.json"))) < 2:
        assert proc.poll() is None, proc.communicate()[1]
        assert time.monotonic() < deadline, "no run finished within 120 s"
        time.sleep(0.02)
    proc.send_signal(signal.SIGTERM)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 143, stderr
    assert [line for line in stderr.splitlines() if "error" in line] == [
        "imufdi: error: terminated by SIGTERM"
    ]
    assert not [p for p in out.rglob("*") if ".tmp" in p.name]
    done = len(list(out.glob("runs/*.json")))
    assert 2 <= done < 24
    resumed = cli(["campaign", spec, "-o", out, "--jobs", "1", "--resume"])  # lock released
    assert resumed.code == 0, resumed.stderr
    assert f"24 runs ({24 - done} executed, {done} resumed, 0 failed)" in resumed.stderr
