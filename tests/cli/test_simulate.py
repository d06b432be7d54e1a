"""imufdi simulate: presets, free options, stdout, reproducibility, bad options."""

from __future__ import annotations

import hashlib

import pytest

from imufdi_cli.mcapio import read_array
from tests.cli.conftest import assert_one_line_error


def test_preset_writes_log(cli, tmp_path):
    out = tmp_path / "a.mcap"
    result = cli(["simulate", "--preset", "paper-table4", "--seed", "3", "-o", out])
    assert result.code == 0, result.stderr
    assert "500 samples of 16 IMUs" in result.stderr
    array, block = read_array(str(out))
    assert array.n_imus == 16 and len(block) == 500


def test_same_seed_same_bytes(cli, tmp_path):
    digests = []
    for name in ("a", "b"):
        out = tmp_path / f"{name}.mcap"
        assert cli(["simulate", "--preset", "conical6", "--seed", "7", "-o", out]).code == 0
        digests.append(hashlib.sha256(out.read_bytes()).hexdigest())
    assert digests[0] == digests[1]


def test_free_options_to_stdout(cli, tmp_path):
    result = cli(
        [
            "simulate",
            "--imus",
            "4",
            "--rate",
            "200Hz",
            "--duration",
            "1s",
            "--motion",
            "turntable",
            "-o",
            "-",
        ]
    )
    assert result.code == 0, result.stderr
    assert result.stdout[:8] == b"\x89MCAP0\r\n"
    path = tmp_path / "s.mcap"
    path.write_bytes(result.stdout)
    array, block = read_array(str(path))
    assert array.n_imus == 4 and len(block) == 200


@pytest.mark.parametrize(
    ("args", "fragment"),
    [
        (["--preset", "nope"], "nope"),
        (["--rate", "100deg"], "100deg"),
        (["--motion", "teleport"], "teleport"),
        (["--duration", "-3s"], "duration"),
    ],
)
def test_bad_options(cli, tmp_path, args, fragment):
    out = tmp_path / "x.mcap"
    result = cli(["simulate", *args, "-o", out])
    assert_one_line_error(result, 2, fragment)
    assert not out.exists()


def test_preset_and_motion_list_their_choices(cli, tmp_path):
    from imufdi_cli.simulate import MOTIONS, PRESETS

    text = cli(["simulate", "--help"]).out
    for name in [*PRESETS, *MOTIONS]:
        assert name in text
    result = cli(["simulate", "--preset", "nope", "-o", tmp_path / "x.mcap"])
    assert_one_line_error(result, 2, "paper-table4")  # the error lists the valid ones


def test_help_does_not_import_the_simulator(fresh_imufdi):
    """The choices come from the registry only when needed (start-up stays light): a fresh
    ``imufdi --help`` (tests/cli/conftest.py: shared with test_app.py)."""
    run = fresh_imufdi(["--help"])
    assert "Commands:" in run.stdout
    unneeded = ("imufdi_cli.simulate", "imufdi_cli.detect", "scipy", "matplotlib")
    assert sorted(m for m in run.modules if m in unneeded) == [], run.stderr
