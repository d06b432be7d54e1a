"""campaign: spec expansion and validation, run keys, failures, resume, summary, executors."""

from __future__ import annotations

import importlib.util
import json
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from imufdi_cli.campaign import (
    CampaignSpec,
    evaluate_summary_gates,
    execute_run,
    load_spec,
    run_campaign,
    run_key,
    summarize,
    summary_markdown,
)
from imufdi_cli.errors import CampaignSpecError, GateError, UsageError

SPEC_200 = """
[campaign]
name = "ci-200"
seeds = [0, 1, 2, 3, 4, 5, 6, 7, 8, 9]
calibrate = "0s:0.6s"

[[base]]
preset = "paper-table4"
options = { duration = "1s" }

[[fault]]
model = "step"
sensor = ["imu0.gyro.x", "imu7.gyro.z"]
at = "0.7s"
amp = ["0.2deg/s", "0.4deg/s", "0.6deg/s", "0.9deg/s", "1.5deg/s"]

[[detector]]
name = "glt"

[[detector]]
name = "pca-parity"
"""

SMALL = """
[campaign]
seeds = [0, 1]
calibrate = "0s:0.6s"

[[base]]
preset = "paper-table4"
options = { duration = "1s" }

[[fault]]
model = "step"
sensor = "imu0.gyro.x"
at = "0.7s"
amp = ["0.3deg/s", "0.9deg/s"]

[[detector]]
name = "glt"
"""


def write_spec(tmp_path: Path, text: str, name: str = "spec.toml") -> Path:
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


# --- spec ------------------------------------------------------------------------------


def test_spec_expands_the_full_matrix(tmp_path):
    spec = load_spec(write_spec(tmp_path, SPEC_200))
    assert spec.name == "ci-200"
    assert len(spec.runs) == 1 * 2 * 5 * 2 * 10
    assert len({run_key(r) for r in spec.runs}) == 200
    faults = sorted({r["faults"][0] for r in spec.runs})
    assert "step:imu0.gyro.x,amp=0.2deg/s,at=0.7s" in faults
    assert len(faults) == 10
    assert {r["detector"] for r in spec.runs} == {"glt", "pca-parity"}
    assert all(r["calibrate"] == [0.0, 0.6] for r in spec.runs)
    assert all(
        r["base"] == {"preset": "paper-table4", "options": {"duration": "1s"}} for r in spec.runs
    )


def test_calibrate_precedence_detector_over_base_over_campaign(tmp_path):
    spec = load_spec(
        write_spec(
            tmp_path,
            """
            [campaign]
            calibrate = "0s:1s"
            [[base]]
            preset = "conical6"
            calibrate = "0s:5s"
            [[base]]
            preset = "paper-table4"
            [[fault]]
            model = "step"
            sensor = "imu0.gyro.z"
            at = "4.5s"  # inside both logs (paper-table4 lasts 5 s)
            amp = "0.5deg/s"
            [[detector]]
            name = "glt"
            [[detector]]
            name = "pca-parity"
            calibrate = "0.5s:4s"
            params = { alpha = [0.01, 0.001] }
            """,
        )
    )
    windows = {
        (r["base"]["preset"], r["detector"], r["params"].get("alpha")): r["calibrate"]
        for r in spec.runs
    }
    assert windows[("conical6", "glt", None)] == [0.0, 5.0]
    assert windows[("paper-table4", "glt", None)] == [0.0, 1.0]
    assert windows[("conical6", "pca-parity", 0.001)] == [0.5, 4.0]
    assert windows[("paper-table4", "pca-parity", 0.01)] == [0.5, 4.0]
    assert len(spec.runs) == 2 * 1 * 3


def test_bases_key_scopes_faults_and_detectors(tmp_path):
    spec = load_spec(
        write_spec(
            tmp_path,
            """
            [campaign]
            seeds = [0, 1]
            [[base]]
            preset = "conical6"
            [[base]]
            preset = "paper-table4"
            name = "t4"
            [[fault]]
            bases = ["conical6"]
            model = "step"
            sensor = "imu5.gyro.z"
            at = "6s"
            amp = ["0.5deg/s", "1deg/s"]
            [[fault]]
            bases = "t4"
            model = "drift"
            sensor = "imu0.gyro.x"
            at = "2.5s"
            rate = "10deg/s^2"
            [[detector]]
            name = "glt"
            [[detector]]
            bases = ["t4"]
            name = "pca-parity"
            """,
        )
    )
    pairs = sorted(
        (r["base"]["preset"], r["detector"], r["faults"][0].split(":")[0]) for r in spec.runs
    )
    assert len(spec.runs) == (2 * 1 + 1 * 2) * 2
    assert set(pairs) == {
        ("conical6", "glt", "step"),
        ("paper-table4", "glt", "drift"),
        ("paper-table4", "pca-parity", "drift"),
    }
    assert "bases" not in spec.runs[0]["faults"][0]


BAD_SPECS = {
    "unknown detector": (
        SMALL.replace('name = "glt"', 'name = "nope"'),
        "detector[0]: unknown detector 'nope'; valid: ",
    ),
    "unknown preset": (
        SMALL.replace('preset = "paper-table4"', 'preset = "moon"'),
        "base[0]: unknown preset 'moon'; valid: conical6, ",
    ),
    "unknown metric": (
        SMALL.replace("[campaign]", '[campaign]\nmetrics = ["far", "speed"]'),
        "campaign.metrics: unknown metric 'speed'; valid: far",
    ),
    "empty matrix": (
        SMALL[: SMALL.index("[[fault]]")] + '[[detector]]\nname = "glt"\n',
        "the fault matrix is empty",
    ),
    "unreadable base log": (
        SMALL.replace(
            'preset = "paper-table4"\noptions = { duration = "1s" }', 'files = "junk.mcap"'
        ),
        "base[0]: unreadable base log",
    ),
    "missing base log": (
        SMALL.replace('preset = "paper-table4"\noptions = { duration = "1s" }', 'files = "*.nope"'),
        "base[0]: no file matches '*.nope'",
    ),
    "unknown campaign key": (
        SMALL.replace("[campaign]", "[campaign]\njobs = 3"),
        "campaign.jobs: unknown key",
    ),
    "unknown detector key": (
        SMALL.replace('name = "glt"', 'name = "glt"\nalpha = 0.1'),
        "detector[0]: unknown key 'alpha'",
    ),
    "bad detector parameter": (
        SMALL.replace('name = "glt"', 'name = "glt"\nparams = { wobble = 1 }'),
        "detector[0]:",
    ),
    "bad calibrate": (
        SMALL.replace('calibrate = "0s:0.6s"', 'calibrate = "2s:1s"'),
        "campaign.calibrate",
    ),
    "bad base calibrate": (
        SMALL.replace('preset = "paper-table4"', 'preset = "paper-table4"\ncalibrate = "3"'),
        "base[0].calibrate",
    ),
    "fault past the array": (
        SMALL.replace('sensor = "imu0.gyro.x"', 'sensor = "imu99.gyro.x"'),
        "fault 'step:imu99.gyro.x",
    ),
    "unknown base name": (
        SMALL.replace('name = "glt"', 'name = "glt"\nbases = ["t4"]'),
        "detector[0].bases: unknown base 't4'; valid: paper-table4",
    ),
    "base without runs": (
        SMALL.replace(
            "[[fault]]", '[[base]]\npreset = "conical6"\n[[fault]]\nbases = "paper-table4"'
        ),
        "base 'conical6' pairs with no [[fault]] and [[detector]]",
    ),
    "bad seeds": (SMALL.replace("seeds = [0, 1]", "seeds = [-1]"), "campaign.seeds"),
    "unknown table": (SMALL + "\n[extra]\nx = 1\n", "unknown table 'extra'"),
    "not toml": ("[campaign\n", "not valid TOML"),
}


@pytest.mark.parametrize("case", sorted(BAD_SPECS))
def test_bad_spec_is_one_line_error_naming_the_key(tmp_path, case):
    text, fragment = BAD_SPECS[case]
    (tmp_path / "junk.mcap").write_bytes(b"not an mcap file at all")
    with pytest.raises(CampaignSpecError) as info:
        load_spec(write_spec(tmp_path, text))
    message = str(info.value)
    assert fragment in message
    assert "\n" not in message


def test_missing_spec_file(tmp_path):
    with pytest.raises(CampaignSpecError, match="cannot read campaign spec"):
        load_spec(tmp_path / "absent.toml")


# --- run keys --------------------------------------------------------------------------

# st.text()'s default alphabet, characters(codec="utf-8"), spelt as the same set (every code
# point but the surrogates): Hypothesis finds the codec's set by encoding all 1.1 million
# code points, 2 s of CPU in every fresh test process, while the category query reads its
# bundled table.
utf8_chars = st.characters(exclude_categories=["Cs"])
json_scalars = st.one_of(
    st.integers(-(10**6), 10**6),
    st.text(utf8_chars, max_size=8),
    st.booleans(),
    st.floats(allow_nan=False),
)


@settings(max_examples=60, deadline=None)
@given(
    st.dictionaries(
        st.text(utf8_chars, min_size=1, max_size=6), json_scalars, min_size=1, max_size=6
    )
)
def test_run_key_ignores_key_order_and_sees_every_value(desc):
    reordered = dict(reversed(list(desc.items())))
    assert run_key(desc) == run_key(reordered)
    assert len(run_key(desc)) == 20
    changed = dict(desc) | {"seed": "different" if desc.get("seed") != "different" else 1}
    assert run_key(changed) != run_key(desc)


# --- one run ---------------------------------------------------------------------------


def test_failed_run_is_recorded_and_campaign_goes_on(tmp_path):
    good = load_spec(write_spec(tmp_path, SMALL)).runs
    bad = dict(good[0]) | {"base": {"preset": "no-such-preset", "options": {}}}
    result = execute_run(bad)
    assert result["ok"] is False
    assert "no-such-preset" in result["error"]
    spec = CampaignSpec(name="mixed", runs=[*good, bad], metrics=["far", "mar"], source="x")
    outcome = run_campaign(spec, tmp_path / "out", jobs=1)
    assert (outcome.total, outcome.executed, outcome.failed) == (5, 5, 1)
    assert outcome.summary["failed"] == 1
    assert outcome.summary["failures"][0]["key"] == run_key(bad)
    csv_lines = (tmp_path / "out" / "runs.csv").read_text().splitlines()
    assert sum(",False," in line for line in csv_lines) == 1
    assert "## Failed runs" in (tmp_path / "out" / "summary.md").read_text()


def test_execute_run_scores_the_faulted_sensor_type(tmp_path):
    run = load_spec(write_spec(tmp_path, SMALL)).runs[-1]  # 0.9 deg/s, seed 1
    result = execute_run(run)
    assert result["ok"], result.get("error")
    gyro = result["metrics"]["gyro"]
    assert gyro["samples"] == 100 and gyro["faulty_samples"] == 30
    assert_allclose(gyro["accuracy"], 1.0 - gyro["far"] - gyro["mar"], atol=1e-12)
    assert gyro["detection_probability"] == 1.0
    assert result["metrics"]["accel"]["faulty_samples"] == 0


# --- resume and outputs -----------------------------------------------------------------


@pytest.mark.campaign_figure  # the one driver test that draws the figure (tests/conftest.py)
def test_resume_skips_done_runs_and_refuses_to_mix_without_it(tmp_path, monkeypatch):
    from imufdi_cli.campaign import driver

    spec = load_spec(write_spec(tmp_path, SMALL))
    first = run_campaign(spec, tmp_path / "out", jobs=1)
    assert (first.executed, first.skipped) == (4, 0)
    if importlib.util.find_spec("matplotlib") is not None:
        png = (tmp_path / "out" / "detection.png").read_bytes()
        assert png[:8] == b"\x89PNG\r\n\x1a\n"
    # the resumed campaign's figure is the same call on the same summary (compared below)
    # and nothing reads it: not drawn again (about 0.15 s of CPU)
    monkeypatch.setattr(driver, "plot_curves", lambda summary, out: None)
    stamps = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "out" / "runs").iterdir()}
    with pytest.raises(UsageError, match="already holds 4 run results; use --resume"):
        run_campaign(spec, tmp_path / "out", jobs=1)
    again = run_campaign(spec, tmp_path / "out", jobs=1, resume=True)
    assert (again.executed, again.skipped) == (0, 4)
    assert stamps == {p.name: p.stat().st_mtime_ns for p in (tmp_path / "out" / "runs").iterdir()}
    assert again.summary == first.summary


def fake_result(
    seed: int, amp: str, far: float, probability: float, sensor: str = "imu0.gyro.x"
) -> dict:
    desc = {
        "base": {"preset": "paper-table4", "options": {}},
        "seed": seed,
        "faults": [f"step:{sensor},amp={amp},at=2.5s"],
        "detector": "glt",
        "params": {},
        "calibrate": [0.0, 2.0],
    }
    gyro = {"far": far, "mar": 0.1, "detection_probability": probability, "faults": []}
    return {"key": run_key(desc), "run": desc, "ok": True, "metrics": {"gyro": gyro}}


def test_summary_means_spreads_and_curves():
    spec = CampaignSpec(
        name="s", runs=[], metrics=["far", "mar", "detection_probability"], source="s.toml"
    )
    results = [
        fake_result(0, "0.9deg/s", 0.02, 1.0),
        fake_result(1, "0.9deg/s", 0.04, 1.0),
        fake_result(2, "0.9deg/s", 0.09, 1.0),
        fake_result(0, "0.3deg/s", 0.05, 0.0),
        fake_result(1, "0.3deg/s", 0.05, 1.0),
    ]
    summary = summarize(spec, results)
    strong = next(g for g in summary["groups"] if g["amplitude"] == "0.9deg/s")
    assert strong["runs"] == 3
    assert_allclose(strong["far"]["mean"], 0.05)
    assert_allclose(strong["far"]["std"], np.std([0.02, 0.04, 0.09], ddof=1))
    (curve,) = summary["curves"]
    assert [p["amplitude"] for p in curve["points"]] == ["0.3deg/s", "0.9deg/s"]
    assert_allclose([p["amplitude_si"] for p in curve["points"]], np.deg2rad([0.3, 0.9]))
    assert_allclose([p["mean"] for p in curve["points"]], [0.5, 1.0])
    text = summary_markdown(summary)
    assert (
        "| paper-table4 | glt | default | step:imu0.gyro.x,at=2.5s | 0.9deg/s | gyro | 3 | 5 ± 3.6 |"
        in text
    )
    assert "0.3deg/s: 50, 0.9deg/s: 100" in text


def test_summary_groups_by_sensor_and_sorts_amplitudes_numerically():
    spec = CampaignSpec(
        name="s", runs=[], metrics=["far", "detection_probability"], source="s.toml"
    )
    results = [
        fake_result(0, "10deg/s", 0.01, 1.0),
        fake_result(0, "1deg/s", 0.02, 1.0),
        fake_result(0, "2deg/s", 0.03, 1.0),
        fake_result(0, "1deg/s", 0.04, 0.0, sensor="imu3.gyro.y"),
    ]
    summary = summarize(spec, results)
    x_groups = [g for g in summary["groups"] if g["sensor"] == "imu0.gyro.x"]
    assert [g["amplitude"] for g in x_groups] == ["1deg/s", "2deg/s", "10deg/s"]
    (other,) = [g for g in summary["groups"] if g["sensor"] == "imu3.gyro.y"]
    assert other["far"]["mean"] == 0.04 and other["runs"] == 1  # not merged with imu0
    assert len(summary["curves"]) == 2
    curve = next(c for c in summary["curves"] if "imu0" in c["fault"])
    assert curve["unit"] == "deg/s"
    assert [p["amplitude_value"] for p in curve["points"]] == [1.0, 2.0, 10.0]


def test_summary_gates():
    spec = CampaignSpec(name="s", runs=[], metrics=["far"], source="s.toml")
    summary = summarize(spec, [fake_result(0, "0.9deg/s", 0.02, 1.0)])
    outcomes = evaluate_summary_gates(summary, ["glt.gyro.far > 0.01", "*.gyro.far > 0.5"])
    assert [failed for _, failed, _ in outcomes] == [True, False]
    with pytest.raises(GateError, match="not aggregated"):
        evaluate_summary_gates(summary, ["glt.gyro.mar > 0.5"])
    with pytest.raises(GateError, match="no campaign results"):
        evaluate_summary_gates(summary, ["glt.accel.far > 0.5"])


# --- the 200-run campaign, local pool against dask -------------------------------------


@pytest.fixture(scope="module")
def campaign_200(tmp_path_factory):
    root = tmp_path_factory.mktemp("campaign200")
    spec = load_spec(write_spec(root, SPEC_200))
    result = run_campaign(spec, root / "pool", jobs=2)
    return spec, root, result


@pytest.mark.slow
def test_campaign_of_200_runs_on_the_preset(campaign_200):
    _, root, result = campaign_200
    assert (result.total, result.executed, result.failed) == (200, 200, 0)
    assert len(list((root / "pool" / "runs").glob("*.json"))) == 200
    summary = json.loads((root / "pool" / "summary.json").read_text())
    # detectors x sensors x amplitudes: faults on different sensors are separate groups
    assert summary["runs"] == 200 and len(summary["groups"]) == 2 * 2 * 5
    assert all(g["runs"] == 10 and g["sensor_type"] == "gyro" for g in summary["groups"])
    for curve in summary["curves"]:  # the strongest step is always detected
        assert curve["points"][-1]["amplitude"] == "1.5deg/s"
        assert curve["points"][-1]["mean"] == 1.0
    for group in summary["groups"]:
        assert_allclose(
            group["accuracy"]["mean"], 1 - group["far"]["mean"] - group["mar"]["mean"], atol=1e-12
        )
    rows = (root / "pool" / "runs.csv").read_text().splitlines()
    assert len(rows) == 1 + 200 * 2  # one row per run and sensor type (gyro, accel)
    assert (root / "pool" / "summary.md").read_text().startswith("# Campaign ci-200")


@pytest.mark.slow
def test_dask_local_cluster_gives_identical_runs_csv(campaign_200):
    pytest.importorskip("dask.distributed")
    spec, root, _ = campaign_200
    result = run_campaign(spec, root / "dask", scheduler="local:2")
    assert (result.total, result.executed, result.failed) == (200, 200, 0)
    assert (root / "dask" / "runs.csv").read_text() == (root / "pool" / "runs.csv").read_text()


@pytest.mark.slow
def test_in_process_gives_identical_outputs_to_the_pool(campaign_200):
    spec, root, _ = campaign_200
    result = run_campaign(spec, root / "serial", jobs=1)
    assert (result.total, result.executed, result.failed) == (200, 200, 0)
    for name in ("runs.csv", "summary.json", "summary.md"):
        assert (root / "serial" / name).read_bytes() == (root / "pool" / name).read_bytes()


def test_bad_scheduler_forms(tmp_path):
    # refused before dask.distributed is imported (installed or not)
    was_imported = "dask.distributed" in sys.modules  # by an earlier test of this process
    spec = load_spec(write_spec(tmp_path, SMALL))
    with pytest.raises(UsageError, match="valid forms are tcp://HOST:PORT and local:N"):
        run_campaign(spec, tmp_path / "o", scheduler="udp://x")
    with pytest.raises(UsageError, match="local:N needs N >= 1"):
        run_campaign(spec, tmp_path / "o2", scheduler="local:0")
    assert was_imported or "dask.distributed" not in sys.modules


JITTER = """
[campaign]
seeds = [0, 1, 2, 3]
calibrate = "0s:0.5s"
match_far = "2%"

[[base]]
preset = "paper-table4"
options = { duration = "1.5s" }

[[fault]]
model = "step"
sensor = "imu0.gyro.x"
at = "0.8s"
at_jitter = "0.4s"
amp = ["0.9deg/s", "1.5deg/s"]

[[detector]]
name = "glt"
"""


def test_at_jitter_draws_onsets_per_seed_and_records_them(tmp_path):
    from imufdi_cli.campaign import jittered_specs
    from imufdi_cli.simulate import config_from_options, simulate_block

    spec = load_spec(write_spec(tmp_path, JITTER))
    assert all(r["at_jitter"] == [0.4] and r["match_far"] == 0.02 for r in spec.runs)
    array, _ = simulate_block(config_from_options("paper-table4", seed=0, duration="0.1s"))
    onsets = {}
    for run in spec.runs:
        applied, (onset,) = jittered_specs(run["faults"], run["at_jitter"], run["seed"], array)
        assert 0.8 <= onset <= 1.2
        assert f"at={onset:.9f}s" in applied[0] and "at=0.8s" not in applied[0]
        # every amplitude of a seed gets the same onset (paired comparisons)
        assert onsets.setdefault(run["seed"], onset) == onset
    assert len(set(onsets.values())) == 4  # seeds differ
    result = run_campaign(spec, tmp_path / "out", jobs=1)
    assert result.failed == 0
    import csv

    with open(tmp_path / "out" / "runs.csv", newline="") as stream:
        rows = list(csv.DictReader(stream))
    assert {"onset_s", "mar_at_far", "target_far", "fault", "sensor"} <= set(rows[0])
    gyro = [row for row in rows if row["sensor_type"] == "gyro"]
    assert {round(float(r["onset_s"]), 6) for r in gyro} == {round(v, 6) for v in onsets.values()}
    assert all(r["target_far"] == "0.02" and r["mar_at_far"] != "" for r in gyro)
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert all("mar_at_far" in g and g["target_far"] == 0.02 for g in summary["groups"])


@pytest.mark.parametrize(
    ("line", "fragment"),
    [
        ('at_jitter = "soon"', "at_jitter"),
        ('at_jitter = "-1s"', "at_jitter"),
    ],
)
def test_bad_at_jitter(tmp_path, line, fragment):
    text = JITTER.replace('at_jitter = "0.4s"', line)
    with pytest.raises(CampaignSpecError, match=fragment):
        load_spec(write_spec(tmp_path, text))


def test_bad_match_far_in_spec(tmp_path):
    with pytest.raises(CampaignSpecError, match="match_far"):
        load_spec(write_spec(tmp_path, JITTER.replace('"2%"', '"200%"')))


# --- the false-alarm budget ----------------------------------------------------------------

BUDGET = """
[campaign]
seeds = [0, 1, 2, 3]
calibrate = "0s:1s"
false_alarms = "1/h"
match_budget = "20/s"

[[base]]
preset = "paper-table4"
options = { duration = "3s" }

[[fault]]
model = "step"
sensor = "imu0.gyro.x"
at = "2.5s"
amp = "0.9deg/s"

[[detector]]
name = "glt"

[[detector]]
name = "glt"
false_alarms = "0/h"
"""


def test_false_alarms_is_set_as_detect_sets_it_campaign_wide_or_per_detector(tmp_path):
    spec = load_spec(write_spec(tmp_path, BUDGET))
    budgets = sorted({run["false_alarms"] for run in spec.runs})
    assert budgets == [0.0, pytest.approx(1 / 3600)]
    assert all(run["params"] == {} for run in spec.runs)  # the parameters as written
    under = execute_run(next(r for r in spec.runs if r["false_alarms"] > 0))
    plain = execute_run(next(r for r in spec.runs if r["false_alarms"] == 0))
    assert under["ok"] and plain["ok"], (under.get("error"), plain.get("error"))
    # the sequential test's reference delays exist only for the run under the budget
    assert under["metrics"]["gyro"]["faults"][0]["reference_delay_s"] > 0
    assert plain["metrics"]["gyro"]["faults"][0]["reference_delay_s"] is None


def test_a_budget_on_a_detector_without_one_is_refused_before_any_run(tmp_path):
    from imufdi_cli.detectors import DETECTORS, detector_class

    without = sorted(n for n in DETECTORS if "false_alarms" not in detector_class(n).PARAMS)
    if not without:
        pytest.skip("every detector honours the budget")
    text = SMALL.replace('name = "glt"', f'name = "{without[0]}"\nfalse_alarms = "1/h"')
    with pytest.raises(CampaignSpecError, match="has no false-alarm budget"):
        load_spec(write_spec(tmp_path, text))


@pytest.mark.parametrize(
    ("line", "fragment"),
    [
        ('false_alarms = "often"', "campaign.false_alarms"),
        ('false_alarms = "-1/h"', "campaign.false_alarms: must be a rate >= 0"),
        ('match_budget = "0/h"', "campaign.match_budget: must be a rate > 0"),
        ('match_budget = "1/parsec"', "campaign.match_budget"),
    ],
)
def test_bad_budget_keys(tmp_path, line, fragment):
    with pytest.raises(CampaignSpecError, match=fragment):
        load_spec(write_spec(tmp_path, SMALL.replace("[campaign]", f"[campaign]\n{line}")))


def test_false_episodes_and_the_matched_budget_are_pooled_over_runs(tmp_path):
    spec = load_spec(write_spec(tmp_path, BUDGET))
    result = run_campaign(spec, tmp_path / "out", jobs=1)
    summary = result.summary
    assert spec.match_budget == pytest.approx(20 * 3600)
    pools = {(p["params"].get("false_alarms"), p["sensor_type"]): p for p in summary["budgets"]}
    assert set(pools) == {(rate, t) for rate in ("1/h", "0/h") for t in ("gyro", "accel")}
    for (rate, sensor_type), pool in pools.items():
        runs = [
            r["metrics"][sensor_type]
            for r in result.results
            if f"{r['run']['false_alarms'] * 3600:g}/h" == rate
        ]
        assert pool["runs"] == 4
        assert pool["false_episodes"] == sum(r["false_episodes"] for r in runs)
        assert pool["fault_free_hours"] == pytest.approx(sum(r["fault_free_hours"] for r in runs))
        assert pool["false_episodes_per_hour"] == pytest.approx(
            pool["false_episodes"] / pool["fault_free_hours"]
        )
    # every group (here the gyro step, per budget) pools its own runs the same way
    for group in summary["groups"]:
        rate = group["false_episodes_per_hour"]
        assert rate["pooled"] and rate["n"] == 4
        assert group["false_episodes_per_hour_upper95"]["mean"] > rate["mean"]
    plain = next(g for g in summary["groups"] if g["params"] == {"false_alarms": "0/h"})
    # 4 x 1.5 s of fault-free gyro time hold 30 false episodes at 20/s: a match exists
    assert pools[("0/h", "gyro")]["threshold_scale_at_budget"] is not None
    assert plain["mar_at_budget"]["n"] == 4 and plain["mar_at_budget"]["mean"] is not None
    assert plain["target_budget_per_hour"] == pytest.approx(72000)
    text = (tmp_path / "out" / "summary.md").read_text()
    assert "## False alarm budget" in text and "false_alarms=1/h" in text
    csv_text = (tmp_path / "out" / "runs.csv").read_text()
    assert "false_episodes_per_hour_upper95" in csv_text.splitlines()[0]
    outcomes = evaluate_summary_gates(
        summary,
        ["glt.gyro.false_episodes_per_hour_upper95 > 1e12", "glt.gyro.mar_at_budget > 2"],
    )
    assert not any(failed for _, failed, _ in outcomes[:4])  # no group past 1e12/h
