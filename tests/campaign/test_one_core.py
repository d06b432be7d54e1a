"""One detection core: a campaign run scores exactly what ``inject | detect | report``
scores on the same log, faults and seed, here on the real MIMU4444 cut with the gyro
samples its hand motion clips (the conditioner's exclusions, the calibration window, the
decision times, the false alarm episodes and the budget figures included)."""

from __future__ import annotations

import json
import math
import textwrap
from pathlib import Path
from typing import Any

import pytest

from imufdi_cli.campaign import load_spec, run_campaign
from tests.cli.conftest import invoke

#: Floating-point figures agree to this (relative and absolute): both sides run the same
#: code on the same samples, cut into different blocks (4096 rows in the campaign, the
#: input's chunks in detect), which moves sums only in their last bits.
TOLERANCE = 1e-9

SPEC = """
[campaign]
name = "one-core"
seeds = [5]
calibrate = "0s:20s"
metrics = ["far", "mar", "fir", "detection_delay_s", "false_episodes_per_hour"]

[[base]]
files = ["{log}"]

[[fault]]
model = "step"
sensor = "imu2.gyro.x"
at = "100s"
until = "240s"
amp = "1.5deg/s"

[[detector]]
name = "glt"
{budget}
"""

#: The sequential test's bank is slow: 2 s of CPU for the budget run alone.
BUDGET = [pytest.mark.slow]


def _same(a: Any, b: Any, where: str) -> None:
    if isinstance(a, dict):
        assert isinstance(b, dict) and set(a) <= set(b), (where, sorted(set(a) - set(b or {})))
        for key in a:
            _same(a[key], b[key], f"{where}.{key}")
    elif isinstance(a, list):
        assert isinstance(b, list) and len(a) == len(b), (where, a, b)
        for i, (x, y) in enumerate(zip(a, b)):
            _same(x, y, f"{where}[{i}]")
    elif isinstance(a, float) or isinstance(b, float):
        assert a is not None and b is not None, (where, a, b)
        assert math.isclose(a, b, rel_tol=TOLERANCE, abs_tol=TOLERANCE), (where, a, b)
    else:
        assert a == b, (where, a, b)


@pytest.mark.parametrize("budget", ["", pytest.param('false_alarms = "1/h"', marks=BUDGET)])
def test_a_campaign_run_scores_what_inject_detect_report_score(
    mimu4444_cut_log: Path, tmp_path: Path, budget: str
) -> None:
    spec_path = tmp_path / "spec.toml"
    spec_path.write_text(textwrap.dedent(SPEC.format(log=mimu4444_cut_log, budget=budget)))
    campaign = run_campaign(load_spec(spec_path), tmp_path / "out", jobs=1)
    assert len(campaign.results) == 1 and all(r["ok"] for r in campaign.results)
    for result in campaign.results:
        run = result["run"]
        budget = ["--false-alarms", "1/h"] if run.get("false_alarms") else []
        applied = result["metrics"]["gyro"]["applied_faults"]
        injected, detected = tmp_path / "inj.mcap", tmp_path / "det.mcap"
        report = tmp_path / "report.json"
        steps = [
            ["inject", mimu4444_cut_log, "--seed", run["seed"], "-o", injected]
            + [arg for spec in applied for arg in ("--fault", spec)],
            # explanations change no figure compared here
            [
                "detect",
                injected,
                "-d",
                "glt",
                "--calibrate",
                "0s:20s",
                "-o",
                detected,
                "--no-explain",
                *budget,
            ],
            ["report", detected, "--json", report, "--match-far", "1%", "-q"],
        ]
        for args in steps:
            done = invoke(args)
            assert done.code == 0, (args, done.stderr)
        entries = json.loads(report.read_text())["results"]
        assert {e["sensor_type"] for e in entries} == set(result["metrics"])
        for entry in entries:
            figures = result["metrics"][entry["sensor_type"]]
            validity = {k: entry.pop(k) for k in ("clipped", "invalid", "excluded", "missing")}
            _same(validity, figures["validity"], f"{entry['sensor_type']}.validity")
            del entry["detector"], entry["sensor_type"]
            _same(entry, figures, f"{run.get('false_alarms')}.{figures['validity']}")
        gyro = result["metrics"]["gyro"]
        # the case the core exists for: clipped gyro samples in fault-free, scored time
        assert gyro["validity"]["clipped"] > 500 and gyro["validity"]["excluded"] > 500
        assert gyro["false_episodes"] is not None and gyro["fault_free_hours"] > 0
        if run.get("false_alarms"):
            fault = gyro["faults"][0]
            assert fault["reference_delay_s"] > 0 and fault["delay_ratio"] is not None
