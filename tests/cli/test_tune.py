"""imufdi tune: the fitness settings reach the tuner; bad ones exit 2 naming the key."""

from __future__ import annotations

import json

from tests.cli.conftest import assert_one_line_error


def test_tune_records_the_fitness(cli, tmp_path, table4_log):
    out = tmp_path / "p.json"
    settings = ["--param", "population=3", "--param", "iterations=1"]
    for fitness in ("cfv", "cfv+delay"):
        result = cli(
            [
                "tune",
                table4_log,
                "--segment",
                "0s:2.5s",
                *settings,
                "--param",
                f"fitness={fitness}",
                "-o",
                out,
            ]
        )
        assert result.code == 0, result.stderr
        tuned = json.loads(out.read_text())
        assert tuned["settings"]["fitness"] == fitness
        assert (tuned["settings"]["validation"] is None) == (fitness == "cfv")
    assert tuned["settings"]["validation"]["step"] == 4.0


def test_tune_rejects_a_bad_fitness_setting(cli, tmp_path, table4_log):
    base = ["tune", table4_log, "--segment", "0s:2.5s", "-o", tmp_path / "p.json"]
    assert_one_line_error(cli([*base, "--param", "fitness=best"]), 2, "fitness")
    assert_one_line_error(cli([*base, "--param", "overlap=50"]), 2, "overlap")


def test_every_tune_option_has_help(cli):
    from imufdi_cli.cli import cli as group

    for param in group.commands["tune"].params:
        if param.param_type_name == "option":
            assert param.help, param.name
    text = cli(["tune", "--help"]).out
    assert "Sensor type whose MVMD parameters are tuned" in text
    assert "Seed of the whale optimisation" in text
