"""CI gates (``--fail-if DETECTOR.TYPE.METRIC OP VALUE``) and the ``--match-far`` rate."""

from __future__ import annotations

import math
import operator
import re
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

from imufdi_cli.errors import GateError, UsageError
from imufdi_cli.metrics import METRIC_NAMES
from imufdi_cli.report.model import Report


def parse_far(text: str) -> float:
    """``"1%"``, ``"0.01"`` -> 0.01; UsageError (exit 2) outside (0, 1) or malformed."""
    raw = text.strip()
    try:
        value = float(raw[:-1]) / 100.0 if raw.endswith("%") else float(raw)
    except ValueError:
        raise UsageError(f"--match-far {text!r} is not a rate (e.g. 1% or 0.01)") from None
    if not (0.0 < value < 1.0) or math.isnan(value):
        raise UsageError(f"--match-far {text!r} must be in (0, 1) (e.g. 1% or 0.01)")
    return value


def parse_budget(text: str) -> float:
    """``"1/h"``, ``"0.5/h"``, ``"2/day"`` -> false episodes per hour; UsageError (exit 2)
    when malformed or not > 0."""
    from imufdi_cli.errors import UnitError
    from imufdi_cli.units import parse_quantity

    try:
        per_second = parse_quantity(text, "frequency", name="--match-budget")
    except UnitError as err:
        raise UsageError(f"--match-budget {text!r}: {err} (e.g. 1/h)") from None
    if not (per_second > 0 and math.isfinite(per_second)):
        raise UsageError(f"--match-budget {text!r} must be a rate > 0 (e.g. 1/h)")
    return per_second * 3600.0


OPERATORS: dict[str, Callable[[float, float], bool]] = {
    ">": operator.gt,
    ">=": operator.ge,
    "<": operator.lt,
    "<=": operator.le,
    "==": operator.eq,
    "!=": operator.ne,
}
_GATE = re.compile(
    r"^\s*([A-Za-z0-9_*-]+)\.([A-Za-z*]+)\.([A-Za-z_][A-Za-z0-9_]*)\s*(>=|<=|==|!=|>|<)\s*"
    r"([+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)\s*(%?)\s*$"
)


@dataclass(frozen=True)
class Gate:
    """``DETECTOR.TYPE.METRIC OP VALUE``: fails when the comparison is true."""

    text: str
    detector: str
    sensor_type: str
    metric: str
    op: str
    value: float


@dataclass
class GateResult:
    gate: Gate
    target: str  # "glt.gyro"
    actual: float | None
    failed: bool
    message: str


def parse_gate(text: str, known_detectors: Iterable[str]) -> Gate:
    """Parse a ``--fail-if`` expression (e.g. ``glt.gyro.far > 0.01`` or ``*.accel.mar >= 5%``).

    Raises GateError (exit 2) naming what is wrong and the valid choices.
    """
    match = _GATE.match(text)
    if match is None:
        raise GateError(
            f"--fail-if {text!r} is not of the form DETECTOR.TYPE.METRIC OP NUMBER "
            "(e.g. 'glt.gyro.far > 0.01'; OP one of > >= < <= == !=)"
        )
    detector, sensor_type, metric, op, number, percent = match.groups()
    known = sorted(known_detectors)
    if detector != "*" and detector not in known:
        raise GateError(
            f"--fail-if {text!r}: unknown detector {detector!r}; valid: {', '.join(known)}, *"
        )
    if sensor_type not in ("gyro", "accel", "mag", "*"):
        raise GateError(
            f"--fail-if {text!r}: unknown sensor type {sensor_type!r}; valid: gyro, accel, mag, *"
        )
    if metric not in METRIC_NAMES:
        raise GateError(
            f"--fail-if {text!r}: unknown metric {metric!r}; valid: {', '.join(METRIC_NAMES)}"
        )
    value = float(number) / (100.0 if percent else 1.0)
    return Gate(text.strip(), detector, sensor_type, metric, op, value)


def evaluate_gates(report: Report, gates: Sequence[Gate]) -> list[GateResult]:
    """Evaluate gates; a gate naming results absent from the log raises GateError.

    A gate whose metric is undefined on this log (e.g. MAR without faulty samples) fails:
    a CI gate must not pass on a figure that could not be computed.
    """
    results = []
    for gate in gates:
        matched = [
            e
            for e in report.entries
            if gate.detector in ("*", e.detector) and gate.sensor_type in ("*", e.sensor_type)
        ]
        if not matched:
            present = ", ".join(f"{e.detector}.{e.sensor_type}" for e in report.entries)
            raise GateError(
                f"--fail-if {gate.text!r}: no results for {gate.detector}.{gate.sensor_type} "
                f"in this log (present: {present or 'none'})"
            )
        for entry in matched:
            actual = entry.metrics.value(gate.metric)
            target = f"{entry.detector}.{entry.sensor_type}.{gate.metric}"
            if actual is None:
                results.append(
                    GateResult(gate, target, None, True, f"{target} is undefined on this log")
                )
                continue
            failed = OPERATORS[gate.op](actual, gate.value)
            verdict = "FAILED" if failed else "passed"
            results.append(
                GateResult(
                    gate,
                    target,
                    actual,
                    failed,
                    f"{verdict}: {target} = {actual:.6g} (fail if {gate.op} {gate.value:g})",
                )
            )
    return results
