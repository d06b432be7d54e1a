"""imufdi inject: truth recorded, inputs untouched, bad specs exit 2 and write nothing."""

from __future__ import annotations

import hashlib
import json

import pytest

from tests.cli.conftest import assert_one_line_error


def _sha(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_inject_records_truth_and_keeps_input(cli, tmp_path, table4_log):
    before = _sha(table4_log)
    out = tmp_path / "f.mcap"
    result = cli(
        [
            "inject",
            table4_log,
            "--fault",
            "drift:imu1.gyro.z,at=1s,until=3s,rate=1deg/s^2",
            "-o",
            out,
        ]
    )
    assert result.code == 0, result.stderr
    assert _sha(table4_log) == before
    info = json.loads(cli(["info", out, "--json"]).out)
    assert info["faults"][0]["model"] == "drift"


def test_same_seed_same_bytes(cli, tmp_path, table4_log):
    outs = []
    for name in ("a", "b"):
        out = tmp_path / f"{name}.mcap"
        args = ["inject", table4_log, "--fault", "noise:imu2.gyro,at=1s,factor=3", "--seed", "5"]
        assert cli([*args, "-o", out]).code == 0
        outs.append(_sha(out))
    assert outs[0] == outs[1]


def test_stdin_to_stdout(cli, table4_log):
    result = cli(
        ["inject", "-", "--fault", "step:imu0.gyro.x,at=2.5s,amp=0.9deg/s", "-o", "-"],
        stdin=table4_log.read_bytes(),
    )
    assert result.code == 0, result.stderr
    assert result.stdout[:8] == b"\x89MCAP0\r\n"


@pytest.mark.parametrize(
    ("spec", "fragment"),
    [
        ("jump:imu0.gyro.x,at=1s,amp=1deg/s", "jump"),
        ("step:imu0.baro.x,at=1s,amp=1deg/s", "baro"),
        ("step:imu99.gyro.x,at=1s,amp=1deg/s", "imu99"),
        ("step:imu0.gyro.x,at=60s,amp=1deg/s", "after the log ends"),
        ("step:imu0.gyro.x,at=2s,until=1s,amp=1deg/s", "until"),
        ("step:imu0.gyro.x,at=1s", "amp"),
        ("step:imu0.gyro.x,at=1s,amp=1g", "amp"),
    ],
)
def test_bad_specs(cli, tmp_path, table4_log, spec, fragment):
    out = tmp_path / "bad.mcap"
    result = cli(["inject", table4_log, "--fault", spec, "-o", out])
    assert_one_line_error(result, 2, fragment)
    assert not out.exists()
    assert not list(tmp_path.iterdir())


def test_no_fault_given(cli, tmp_path, table4_log):
    assert_one_line_error(cli(["inject", table4_log, "-o", tmp_path / "x.mcap"]), 2, "no fault")


def test_refuses_to_overwrite_input(cli, table4_log):
    before = _sha(table4_log)
    result = cli(
        ["inject", table4_log, "--fault", "step:imu0.gyro.x,at=1s,amp=1deg/s", "-o", table4_log]
    )
    assert_one_line_error(result, 2, "input")
    assert _sha(table4_log) == before


def test_corrupt_input_chunk_is_named_in_a_warning(cli, tmp_path, table4_log):
    from tests.cli.test_info import _damaged_second_chunk

    data, offset = _damaged_second_chunk(table4_log)
    path = tmp_path / "bad.mcap"
    path.write_bytes(data)
    out = tmp_path / "out.mcap"
    result = cli(["inject", path, "--fault", "step:imu0.gyro.x,at=1s,amp=1deg/s", "-o", out])
    assert result.code == 0, result.stderr
    assert f"warning: chunk at byte {offset} skipped: " in result.stderr
