"""Simulation and fault injection outputs are those recorded before the package split.

``imufdi_cli.simulate`` and ``imufdi_cli.faults`` were split into packages by concern with
behaviour unchanged. The records were made with the single-module code: every preset with
its own seed, every fault model, streaming injection in uneven blocks, and ``inject_file``
on a simulated MCAP read back. Each array is stored as its fingerprint
(:func:`tests.references.fingerprint`), compared to :data:`RTOL`; the fault records (specs
in SI, ids, seed), timestamps and message counts to :data:`SPEC_RTOL` (floats) and exactly
(integers, strings).

Re-record (only for a deliberate change of outputs, saying why in the commit):
``PYTHONPATH=. python tests/test_reference_outputs.py``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import pytest

from imufdi_cli.faults import FaultInjector, inject_file, parse_fault_spec
from imufdi_cli.log import ImuBlock, iter_blocks
from imufdi_cli.mcapio import ImuArrayReader
from imufdi_cli.pipeline import simulate_file
from imufdi_cli.simulate import preset, simulate_block
from tests.references import assert_fingerprint_close, assert_tree_close, fingerprint

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


#: Relative tolerance of the samples (of an array's scale). A simulated sample is a few
#: dozen operations on seeded draws: sines, cosines and exponentials of the motion (numpy's
#: SIMD implementations of these differ by a few ulp), 3x3 rotations and sums of error
#: terms, so each lies within ~1e-14 of its magnitude on any machine, and an array's
#: fingerprint within ~1e-15 of its scale (measured across numpy's AVX-512, AVX2 and
#: SSE4.2 loops, five OpenBLAS kernels and numpy 2.0 against 2.4: at most 3.4e-16). A real
#: change is far larger: one sample changed by 1e-12 of the array's sum |x| fails it.
RTOL = 1e-12
#: Relative tolerance of the floats of the fault records: unit conversions of the specs
#: (products and quotients of decimal constants, correctly rounded on any IEEE-754
#: machine) and the preset's noise levels: a libm's last bit at most (1e-15 ~ 4.5 ulp).
SPEC_RTOL = 1e-15


def _is_fingerprint(value: Any) -> bool:
    return isinstance(value, list) and len(value) == 5 and all(isinstance(v, float) for v in value)


def _close(actual: Any, expected: Any, where: str) -> None:
    if isinstance(expected, dict):
        assert isinstance(actual, dict) and sorted(actual) == sorted(expected), where
        for key in expected:
            if key == "json":  # a fault record as the injector serialises it
                assert_tree_close(
                    json.loads(actual[key]), json.loads(expected[key]), SPEC_RTOL, f"{where}.json"
                )
            else:
                _close(actual[key], expected[key], f"{where}.{key}")
    elif _is_fingerprint(expected):
        assert_fingerprint_close(actual, expected, RTOL, where)
    else:
        assert_tree_close(actual, expected, SPEC_RTOL, where)


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
