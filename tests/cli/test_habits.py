"""Shell and CLI habits: completion of file names, a closed stdout, --start/--end as
people give times, UTC times in info, units as typed, --json heads, -q messages."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from click.shell_completion import ShellComplete

from imufdi_cli.cli.app import cli as group
from imufdi_cli.cli.ui import JSON_FORMAT_VERSION
from imufdi_cli.errors import UnitError
from imufdi_cli.units import UnixTime, parse_quantity, parse_time_point
from tests.cli.conftest import assert_one_line_error

ROOT = Path(__file__).resolve().parents[2]


def _completions(args: list[str], incomplete: str) -> list[tuple[str, str]]:
    completer = ShellComplete(group, {}, "imufdi", "_IMUFDI_COMPLETE")
    return [(item.type, item.value) for item in completer.get_completions(args, incomplete)]


@pytest.mark.parametrize(
    ("args", "kind"),
    [
        (["info"], "file"),
        (["detect"], "file"),
        (["detect", "x.mcap", "-o"], "file"),
        (["detect", "x.mcap", "--array"], "file"),
        (["report", "x.mcap", "--plot"], "file"),
        (["ingest", "cap.bin", "--layout"], "file"),
        (["campaign", "spec.toml", "-o"], "dir"),
        (["demo", "--keep"], "dir"),
    ],
)
def test_path_arguments_complete_file_names(args, kind):
    """``imufdi info s<TAB>``: click hands the shell a file (or dir) completion, which
    bash's ``compgen -f`` / zsh's ``_files`` fill with names."""
    assert _completions(args, "s") == [(kind, "s")]


def test_bash_completes_a_file_name_in_a_real_shell(tmp_path):
    """The completion script click generates, run by bash, lists the matching file."""
    if not Path("/bin/bash").exists():
        pytest.skip("no bash")
    (tmp_path / "sample.mcap").write_bytes(b"")
    (tmp_path / "other.mcap").write_bytes(b"")
    env = {
        **os.environ,
        "COMP_WORDS": "imufdi info s",
        "COMP_CWORD": "2",
        "_IMUFDI_COMPLETE": "bash_complete",
        "PYTHONPATH": str(ROOT),
    }
    out = subprocess.run(
        [sys.executable, "-c", "from imufdi_cli.cli import main; main()"],
        env=env,
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.stdout.split("\n")[0] == "file,s"  # bash then runs compgen -f -- s
    listing = subprocess.run(
        ["/bin/bash", "-c", "compgen -f -- s"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert listing.stdout.split() == ["sample.mcap"]


def test_options_and_detectors_still_complete():
    assert ("plain", "health") in _completions(["detect", "x.mcap", "-d"], "he")


@pytest.mark.parametrize("command", ["simulate", "detect"])
def test_a_closed_stdout_ends_quietly_with_exit_0(tmp_path, command):
    """``imufdi simulate -o - | head -c1``: exit 0 (documented), nothing on stderr."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    args = ["simulate", "--duration", "20s", "-o", "-"]
    if command == "detect":
        log = tmp_path / "in.mcap"
        subprocess.run(
            [sys.executable, "-m", "imufdi_cli", *args[:-1], str(log)],
            env=env,
            check=True,
            capture_output=True,
            timeout=120,
        )
        args = ["detect", str(log), "-d", "glt", "-o", "-"]
    process = subprocess.Popen(
        [sys.executable, "-m", "imufdi_cli", *args],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    assert process.stdout is not None and process.stderr is not None
    assert len(process.stdout.read(1)) == 1
    process.stdout.close()  # what `head -c1` does
    stderr = process.stderr.read()
    assert process.wait(timeout=120) == 0
    assert stderr == b""


def test_time_points():
    assert parse_time_point("30s") == 30.0 and not isinstance(parse_time_point("30"), UnixTime)
    assert parse_time_point("2min") == 120.0
    iso = parse_time_point("2023-11-14T22:13:30Z")
    assert isinstance(iso, UnixTime) and iso == 1_700_000_010.0
    assert parse_time_point("2023-11-14T23:13:30+01:00") == 1_700_000_010.0
    assert parse_time_point("2023-11-14T22:13:30.250Z") == 1_700_000_010.25
    unix = parse_time_point("1700000002")
    assert isinstance(unix, UnixTime) and unix == 1_700_000_002.0
    with pytest.raises(UnitError, match="no time zone; add Z"):
        parse_time_point("2023-11-14T22:13:30")
    with pytest.raises(UnitError, match="ISO 8601 UTC time"):
        parse_time_point("-11-14T22:13:22Z")


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    from tests.cli.conftest import invoke

    log = tmp_path_factory.mktemp("habits") / "sim.mcap"
    assert invoke(["simulate", "--duration", "30s", "-o", log]).code == 0
    return log


def test_detect_window_in_iso_utc_tests_10_s(cli, tmp_path, simulated):
    """The simulated log starts at 2023-11-14T22:13:20Z (t0 1700000000 s)."""
    out = tmp_path / "d.mcap"
    result = cli(
        [
            "detect",
            simulated,
            "-d",
            "glt",
            "--start",
            "2023-11-14T22:13:30Z",
            "--end",
            "2023-11-14T22:13:40Z",
            "-o",
            out,
            "--json",
            "-",
        ]
    )
    assert result.code == 0, result.stderr
    summary = json.loads(result.stdout)
    assert summary["samples"] == 1000  # 10 s at 100 Hz
    unix = cli(
        [
            "detect",
            simulated,
            "-d",
            "glt",
            "--start",
            "1700000010",
            "--end",
            "1700000020",
            "-o",
            out,
            "--json",
            "-",
        ]
    )
    assert json.loads(unix.stdout)["samples"] == 1000
    report = cli(["report", out, "--start", "2023-11-14T22:13:35Z", "--json", "-"])
    assert report.code == 0, report.stderr


def test_a_window_without_samples_warns(cli, tmp_path, simulated):
    result = cli(
        ["detect", simulated, "-d", "glt", "--start", "1800000000", "-o", tmp_path / "d.mcap"]
    )
    assert result.code == 0
    assert "warning: --start/--end holds no sample" in result.stderr
    assert "from 2023-11-14T22:13:20Z" in result.stderr


def test_info_shows_utc_start_and_end(cli, simulated):
    result = cli(["info", simulated, "--json", "-"])
    data = json.loads(result.stdout)
    assert data["start_utc"] == "2023-11-14T22:13:20Z"
    assert data["end_utc"] == "2023-11-14T22:13:49.990Z"
    text = cli(["info", simulated]).out
    assert "2023-11-14T22:13:20Z" in text and "2023-11-14T22:13:49.990Z" in text


@pytest.mark.parametrize(
    ("text", "dimension", "si"),
    [
        ("0.9°/s", "angular_rate", 0.9 * 3.141592653589793 / 180),
        ("0.2m/s²", "acceleration", 0.2),
        ("0.2 m/s^2", "acceleration", 0.2),
        ("1g", "acceleration", 9.80665),
        ("50µT", "magnetic_field", 50e-6),
        ("50μT", "magnetic_field", 50e-6),
        ("0.5G", "magnetic_field", 0.5e-4),
        ("150%", "dimensionless", 1.5),
        ("10°/s²", "angular_acceleration", 10 * 3.141592653589793 / 180),
    ],
)
def test_units_as_people_type_them(text, dimension, si):
    assert parse_quantity(text, dimension) == pytest.approx(si, rel=1e-12)  # one rounding


def test_capital_g_is_gauss_and_refused_as_an_acceleration_with_a_hint():
    with pytest.raises(UnitError, match=r"G is gauss .* write g for standard gravity"):
        parse_quantity("16G", "acceleration")


def test_fault_amplitudes_in_typed_units(cli, tmp_path, simulated):
    out = tmp_path / "f.mcap"
    result = cli(
        [
            "inject",
            simulated,
            "--fault",
            "step:imu0.gyro.x,at=2s,amp=0.9°/s",
            "--fault",
            "step:imu1.accel.x,at=2s,amp=0.2m/s²",
            "-o",
            out,
            "--json",
            "-",
        ]
    )
    assert result.code == 0, result.stderr


def _json_of(cli, args):
    result = cli([*args, "--json", "-"])
    assert result.code == 0, result.stderr
    return json.loads(result.stdout)


def test_every_json_object_starts_with_format_version_and_command(cli, tmp_path, simulated):
    detected = tmp_path / "d.mcap"
    runs = {
        "info": ["info", simulated],
        "simulate": ["simulate", "--duration", "1s", "-o", tmp_path / "s.mcap"],
        "inject": [
            "inject",
            simulated,
            "--fault",
            "step:imu0.gyro.x,at=1s,amp=1deg/s",
            "-o",
            tmp_path / "i.mcap",
        ],
        "detect": ["detect", simulated, "-d", "glt", "-o", detected],
        "report": ["report", detected],
    }
    for command, args in runs.items():
        data = _json_of(cli, args)
        assert list(data)[:2] == ["format_version", "command"], command
        assert data["format_version"] == JSON_FORMAT_VERSION and data["command"] == command


def test_a_failed_gate_under_quiet_says_what_failed(cli, tmp_path, simulated):
    detected = tmp_path / "d.mcap"
    assert cli(["detect", simulated, "-d", "glt", "-o", detected, "-q"]).code == 0
    result = cli(["report", detected, "--fail-if", "glt.gyro.far > -1", "-q"])
    assert_one_line_error(result, 1, "glt.gyro.far > -1 (actual ")
    assert "above" not in result.stderr
    loud = cli(["report", detected, "--fail-if", "glt.gyro.far > -1"])
    assert "the report above shows every figure" in loud.stderr


def test_a_report_window_without_samples_warns(cli, tmp_path, simulated):
    detected = tmp_path / "d.mcap"
    assert cli(["detect", simulated, "-d", "glt", "-o", detected, "-q"]).code == 0
    result = cli(["report", detected, "--start", "2033-01-01T00:00:00Z"])
    assert result.code == 0
    assert "warning: --start/--end holds no status sample" in result.stderr
    assert "the status starts at 2023-11-14T22:13:20Z" in result.stderr
    inside = cli(["report", detected, "--start", "2023-11-14T22:13:30Z"])
    assert "holds no status sample" not in inside.stderr
