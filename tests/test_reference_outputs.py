"""Simulation and fault injection outputs are those recorded before the package split.

``imufdi_cli.simulate`` and ``imufdi_cli.faults`` were split into packages by concern
with behaviour unchanged. The fingerprints below were recorded with the
single-module code (commit e7e928c): every preset with its own seed, every fault model,
streaming injection in uneven blocks, and ``inject_file`` on a simulated MCAP read back. A
fingerprint is the NaN count and (sum, sum of squares, sum weighted by sin(0.37 k + 1)) of
the other values, compared to 1e-12 of their sum |x|: any change of a sample beyond rounding shows,
while a different summation order on another CPU does not. The fault records (JSON: specs
in SI, ids, seed) are compared exactly.

Re-record (only for a deliberate change of outputs, saying why in the commit):
``PYTHONPATH=. python tests/test_reference_outputs.py``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from imufdi_cli.faults import FaultInjector, inject_file, parse_fault_spec
from imufdi_cli.log import ImuBlock, iter_blocks
from imufdi_cli.mcapio import ImuArrayReader
from imufdi_cli.pipeline import simulate_file
from imufdi_cli.simulate import preset, simulate_block

#: preset -> (seed, duration, fault specs covering every model on its sensors)
CASES: dict[str, tuple[int, str, tuple[str, ...]]] = {
    "paper-table4": (
        3,
        "3s",
        (
            "step:imu0.gyro.x,at=1s,amp=0.9deg/s",
            "drift:imu1.accel.z,at=0.5s,until=2.5s,rate=0.01g/s",
            "noise:imu2.gyro,at=1s,duration=1s,sigma=0.3deg/s",
            "stuck:imu3.accel.y,at=2s",
            "scale:imu4.gyro.z,at=0s,ppm=20000",
            "spikes:imu5.gyro,at=0.2s,rate=5Hz,amp=1deg/s,width=3",
            "noise:imu0.gyro.x,at=1.5s,factor=3",
        ),
    ),
    "conical6": (4, "2s", ("step:imu5.gyro.z,at=1s,amp=0.5deg/s", "stuck:imu1.gyro.z,at=0s")),
    "wearable12": (5, "2s", ("noise:imu0.accel.x,at=0.5s,until=1.5s,factor=3",)),
    "quadrotor-marg": (
        6,
        "2s",
        ("step:imu0.accel.x,at=1s,amp=0.5g", "drift:imu0.mag,at=0.5s,rate=1uT/s"),
    ),
}
INJECT_SEED = 11
FILE_FAULTS = (
    "step:imu0.gyro.x,at=0.5s,amp=0.9deg/s",
    "spikes:imu2.accel,at=0s,rate=4Hz,amp=0.1g,width=2",
)


def fingerprint(values: np.ndarray) -> list[float]:
    """(NaN count, sum, sum of squares, sin-weighted sum, sum |x|) of an array, NaN as 0."""
    raw = np.asarray(values, dtype=np.float64).ravel()
    x = np.where(np.isnan(raw), 0.0, raw)
    weights = np.sin(0.37 * np.arange(x.size) + 1.0)
    sums = [x.sum(), (x * x).sum(), (x * weights).sum(), np.abs(x).sum()]
    return [float(np.isnan(raw).sum()), *(float(v) for v in sums)]


def block_fingerprints(block: ImuBlock) -> dict[str, Any]:
    out: dict[str, Any] = {"t_ns": [int(block.t_ns[0]), int(block.t_ns[-1]), len(block)]}
    for sensor_type in ("gyro", "accel", "mag"):
        values = block.get(sensor_type)
        out[sensor_type] = None if values is None else fingerprint(values)
    return out


def simulated_and_injected() -> dict[str, Any]:
    record: dict[str, Any] = {}
    for name, (seed, duration, specs) in CASES.items():
        array, block = simulate_block(preset(name, seed=seed, duration=duration))
        faults = [parse_fault_spec(spec, array) for spec in specs]
        injector = FaultInjector(faults, array, seed=INJECT_SEED, t0_ns=int(block.t_ns[0]))
        parts = [injector.apply_block(part) for part in iter_blocks(block, 37)]
        record[name] = {
            "simulated": block_fingerprints(block),
            "injected": block_fingerprints(ImuBlock.concatenate(parts)),
            "faults": injector.metadata(),
        }
    return record


def inject_file_outputs(tmp: Path) -> dict[str, Any]:
    clean, faulty = tmp / "clean.mcap", tmp / "faulty.mcap"
    simulate_file("paper-table4", str(clean), seed=9, options={"duration": "2s"})
    result = inject_file(clean, faulty, FILE_FAULTS, [], seed=INJECT_SEED)
    block = ImuBlock.concatenate(ImuArrayReader(str(faulty)).blocks())
    return {
        "injected": block_fingerprints(block),
        "faults": [fault.to_dict() for fault in result.faults],
        "t0_ns": result.t0_ns,
        "messages": [result.messages, result.messages_patched, result.truth_messages],
    }


def record(tmp: Path) -> dict[str, Any]:
    return {"blocks": simulated_and_injected(), "file": inject_file_outputs(tmp)}


def _close(actual: Any, expected: Any, where: str) -> None:
    if isinstance(expected, dict):
        assert isinstance(actual, dict) and sorted(actual) == sorted(expected), where
        for key in expected:
            _close(actual[key], expected[key], f"{where}.{key}")
    elif (
        isinstance(expected, list)
        and len(expected) == 5
        and all(isinstance(v, float) for v in expected)
    ):
        assert actual[0] == expected[0], f"{where}: NaN count"
        scale = 1e-12 * max(expected[4], 1.0)
        assert np.allclose(actual[1:], expected[1:], rtol=0.0, atol=scale), where
    else:
        assert actual == expected, where


REFERENCE = Path(__file__).with_suffix(".json")


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    return record(tmp_path_factory.mktemp("reference"))


def test_simulation_and_block_injection_match_the_pre_split_outputs(recorded) -> None:
    expected = json.loads(REFERENCE.read_text(encoding="utf-8"))
    _close(json.loads(json.dumps(recorded["blocks"])), expected["blocks"], "blocks")


def test_inject_file_matches_the_pre_split_output(recorded) -> None:
    expected = json.loads(REFERENCE.read_text(encoding="utf-8"))
    _close(json.loads(json.dumps(recorded["file"])), expected["file"], "file")


if __name__ == "__main__":  # re-record (see the module docstring)
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        data = record(Path(tmp))
    REFERENCE.write_text(json.dumps(data, indent=1, sort_keys=True) + "\n", encoding="utf-8")
    print(f"wrote {REFERENCE}", file=sys.stderr)
