"""--fail-if gates and the --match-far rate on a hand-made report."""

from __future__ import annotations

import pytest

from imufdi_cli.errors import GateError, UsageError
from imufdi_cli.report.gates import evaluate_gates, parse_far, parse_gate
from tests.report.reports import KNOWN, hand_made_report


def test_parse_gate_forms():
    gate = parse_gate("glt.gyro.far > 0.01", KNOWN)
    assert (gate.detector, gate.sensor_type, gate.metric, gate.op, gate.value) == (
        "glt",
        "gyro",
        "far",
        ">",
        0.01,
    )
    assert parse_gate("*.accel.mar>=5%", KNOWN).value == pytest.approx(0.05)
    assert parse_gate(" pca-parity.*.detection_delay_s <= 1e-1 ", KNOWN).op == "<="


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ("glt.gyro.far", "not of the form"),
        ("glt.gyro.far >> 1", "not of the form"),
        ("glt.gyro.far > abc", "not of the form"),
        ("nope.gyro.far > 1", "unknown detector 'nope'; valid: glt, pca-parity"),
        ("glt.baro.far > 1", "unknown sensor type 'baro'"),
        ("glt.gyro.speed > 1", "unknown metric 'speed'"),
    ],
)
def test_parse_gate_errors(text, fragment):
    with pytest.raises(GateError, match=fragment.replace("(", r"\(")) as info:
        parse_gate(text, KNOWN)
    assert info.value.exit_code == 2
    assert "\n" not in str(info.value)


def test_evaluate_gates_pass_fail_and_undefined():
    report = hand_made_report()
    gates = [
        parse_gate("glt.gyro.far > 0.05", KNOWN),  # 0.04: passes
        parse_gate("glt.gyro.mar > 0.05", KNOWN),  # 0.10: fails
        parse_gate("glt.*.fir >= 2%", KNOWN),  # 1/45 = 2.2 %: fails
    ]
    results = evaluate_gates(report, gates)
    assert [r.failed for r in results] == [False, True, True]
    assert results[0].actual == pytest.approx(0.04)
    assert results[1].actual == pytest.approx(0.10)
    assert results[2].actual == pytest.approx(1 / 45)
    # undefined metric fails the gate
    no_truth = hand_made_report(with_truth=False)
    no_truth.entries[0].metrics.mar = None
    (undefined,) = evaluate_gates(no_truth, [parse_gate("glt.gyro.mar > 0.5", KNOWN)])
    assert undefined.failed and "undefined" in undefined.message


def test_gate_naming_absent_results_is_usage_error():
    with pytest.raises(GateError, match=r"no results for pca-parity\.gyro.*present: glt\.gyro"):
        evaluate_gates(hand_made_report(), [parse_gate("pca-parity.gyro.far > 0.1", KNOWN)])


@pytest.mark.parametrize(("text", "value"), [("1%", 0.01), (" 0.02 ", 0.02), ("99.5%", 0.995)])
def test_parse_far_accepts_rates_and_percentages(text, value):
    assert parse_far(text) == pytest.approx(value, rel=1e-15)


@pytest.mark.parametrize("text", ["0", "1", "100%", "-1%", "nan", "abc", "%"])
def test_parse_far_rejects_what_is_not_a_rate_in_0_1(text):
    with pytest.raises(UsageError, match="--match-far") as info:
        parse_far(text)
    assert info.value.exit_code == 2
