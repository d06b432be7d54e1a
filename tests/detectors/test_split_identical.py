"""bank, cnn-map, pca-parity and woa-mvmd-glt give the outputs recorded from their
single-module code, before each became a package split by concern with behaviour unchanged.

Each case runs a detector on a fixed seeded simulated log with injected faults, streamed in
uneven blocks, and compares every array of every :class:`DetectionBlock` (statistic,
threshold, alarm, isolated, amplitude, scores, isolated_set, amplitudes) and the metadata
with ``data/split_identical.json``. Those values are the single-module code's: they were
recorded on a CPU configuration (numpy's AVX2 loops, OpenBLAS's Haswell kernel) on which
every array and every metadata document of the current code had the SHA-256 of the
single-module records, byte for byte.

Integer and boolean arrays (alarms, isolated sensors) are compared exactly, by SHA-256 of
their bytes. Float arrays are compared by :func:`tests.references.fingerprint` and the
metadata as a tree, both to :data:`RTOL` (see there). The metadata is compared as it
means, not as bytes: the cnn-map model's weights (an npz archive, whose zip layout changes
with numpy's version) by fingerprint, and the pca-parity training mean in the PCA basis by
its norm (see :func:`comparable_metadata`).

Re-record (only for a deliberate change of outputs, saying why in the commit):
``PYTHONPATH=. python tests/detectors/test_split_identical.py``.
"""

from __future__ import annotations

import base64
import hashlib
import io
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from imufdi_cli.detectors import make_detector
from imufdi_cli.detectors.base import DetectionBlock
from imufdi_cli.faults import FaultInjector, parse_fault_spec
from imufdi_cli.log import ImuBlock
from imufdi_cli.simulate import preset, simulate_block
from tests.references import assert_fingerprint_close, assert_tree_close, fingerprint

RECORD = Path(__file__).parent / "data" / "split_identical.json"
FIELDS = (
    "statistic",
    "threshold",
    "alarm",
    "isolated",
    "amplitude",
    "scores",
    "isolated_set",
    "amplitudes",
)

#: Relative tolerance of the float outputs and metadata (of an array's or a vector's scale;
#: of its own magnitude for a scalar). The detectors' outputs are least-squares fits,
#: recursive filters, eigen-decompositions and sums over at most 1200 samples of up to 48
#: sensors: with eps = 2.2e-16 per operation, ~1e3 operations per sum and conditioning up
#: to ~1e3, rounding reaches of the order of 1e-10 of a result's scale at most. Measured
#: between numpy's AVX-512, AVX2 and SSE4.2 loops, OpenBLAS's SkylakeX, Haswell,
#: Sandybridge, Nehalem and Prescott kernels, and numpy 2.0 / scipy 1.13 against
#: numpy 2.4 / scipy 1.17: at most 1.1e-12 (outputs) and 8e-12 (metadata). A real change
#: is far larger: mvmd_alpha or bank's tau moved by 1e-7 of itself fails the outputs.
RTOL = 1e-9

#: case -> (detector, params, preset, seed, duration s, fault specs, calibration s, block sizes)
CASES: dict[
    str, tuple[str, dict[str, str], str, int, float, tuple[str, ...], float, tuple[int, ...]]
] = {
    "bank-marg": (
        "bank",
        {},
        "quadrotor-marg",
        3,
        8.0,
        ("step:imu0.gyro.z,at=5s,amp=0.5rad/s", "drift:imu0.gyro.x,at=5s,rate=0.1rad/s^2"),
        2.0,
        (97, 250, 31),
    ),
    "bank-array-table4": (
        "bank",
        {"mode": "array"},
        "paper-table4",
        4,
        6.0,
        ("step:imu0.gyro.x,at=3s,amp=0.9deg/s", "step:imu3.gyro.y,at=4s,amp=1.5deg/s"),
        2.0,
        (64, 200),
    ),
    "cnn-map-wearable12": (
        "cnn-map",
        {"epochs": "4", "patience": "2", "mapping_test": "alarm"},
        "wearable12",
        1,
        12.0,
        ("noise:imu0.accel.x,at=8s,until=11s,factor=3",),
        6.0,
        (250, 77),
    ),
    "pca-parity-conical6": (
        "pca-parity",
        {},
        "conical6",
        7,
        6.0,
        ("step:imu1.gyro,at=4s,amp=0.5deg/s", "drift:imu2.gyro,at=3s,rate=0.2deg/s^2"),
        3.0,
        (90, 203, 17),
    ),
    "pca-parity-wearable12": (
        "pca-parity",
        {"leak": "none"},
        "wearable12",
        8,
        5.0,
        ("step:imu4.accel.z,at=3.5s,amp=0.2m/s^2",),
        2.5,
        (128, 41),
    ),
    "woa-mvmd-glt-tuned": (
        "woa-mvmd-glt",
        {
            "population": "3",
            "iterations": "2",
            "tune_samples": "150",
            "types": "gyro",
            "outliers": "variance",
            "combine": "min",
        },
        "paper-table4",
        5,
        5.0,
        ("step:imu0.gyro.x,at=3s,amp=0.9deg/s",),
        2.0,
        (64, 13, 200),
    ),
    "woa-mvmd-glt-fixed-clip": (
        "woa-mvmd-glt",
        {"K": "2", "mvmd_alpha": "2000", "outliers": "clip", "combine": "centre"},
        "paper-table4",
        6,
        4.0,
        ("spikes:imu2.gyro,at=2.5s,rate=4Hz,amp=1deg/s,width=2",),
        2.0,
        (50, 111),
    ),
}


def _digest(values: np.ndarray) -> dict[str, Any]:
    """An output array as stored: dtype and shape; SHA-256 of the bytes of an integer or
    boolean array, the :func:`fingerprint` of a float one."""
    array = np.ascontiguousarray(values)
    out: dict[str, Any] = {"dtype": str(array.dtype), "shape": list(array.shape)}
    if array.dtype.kind in "biu":
        out["sha256"] = hashlib.sha256(array.tobytes()).hexdigest()
    else:
        out["fingerprint"] = fingerprint(array)
    return out


#: metadata keys that change between runs of the same code: tuning wall time, and whether
#: the tuning came from the in-process cache of an earlier identical fit.
VOLATILE = frozenset({"seconds", "reused"})

#: parameters that the single-module code did not have, with the value under which a
#: detector behaves as it did then: dropped from ``metadata.params`` when they have that
#: value (any other value is compared, and fails). ``false_alarms_per_hour``: the
#: false-alarm budget (every detector's ``false_alarms``, named in its metadata as glt
#: names it); 0 is the papers' per-sample test that the records hold.
ADDED_PARAMS: dict[str, Any] = {"false_alarms_per_hour": 0.0}


def without_added_params(metadata: dict[str, Any]) -> dict[str, Any]:
    """``metadata`` without the :data:`ADDED_PARAMS` at their recorded behaviour's value."""
    params = metadata.get("params")
    if not isinstance(params, dict):
        return metadata
    kept = {k: v for k, v in params.items() if k not in ADDED_PARAMS or v != ADDED_PARAMS[k]}
    return {**metadata, "params": kept}


def comparable_metadata(value: Any) -> Any:
    """The metadata (JSON-like) as it is compared: without the :data:`VOLATILE` keys, at
    any depth; ``model_npz_base64`` (cnn-map's weights: a zip archive, whose layout numpy
    changed between versions) as each array's fingerprint and the header's JSON;
    ``training_mean`` (pca-parity: the training mean in the basis of the principal
    directions, whose signs and, among near-equal eigenvalues, orientation are the
    eigen-solver's choice and differ between BLAS kernels) as its norm, which that choice
    leaves unchanged."""
    if isinstance(value, dict):
        out = {}
        for key, item in value.items():
            if key in VOLATILE:
                continue
            if key == "model_npz_base64":
                out[key] = _npz_contents(item)
            elif key == "training_mean":
                out[key] = float(np.linalg.norm(item))
            else:
                out[key] = comparable_metadata(item)
        return out
    if isinstance(value, list | tuple):
        return [comparable_metadata(v) for v in value]
    return value


def _npz_contents(text: str) -> dict[str, Any]:
    with np.load(io.BytesIO(base64.b64decode(text))) as archive:
        return {
            name: json.loads(str(archive[name]))
            if archive[name].dtype.kind == "U"
            else {"shape": list(archive[name].shape), "fingerprint": fingerprint(archive[name])}
            for name in sorted(archive.files)
        }


def _log(name: str) -> tuple[Any, ImuBlock]:
    _, _, preset_name, seed, duration, faults, _, _ = CASES[name]
    array, clean = simulate_block(preset(preset_name, seed=seed, duration=duration))
    specs = [parse_fault_spec(s, array) for s in faults]
    injector = FaultInjector(specs, array, seed=seed, t0_ns=int(clean.t_ns[0]))
    return array, injector.apply_block(clean.copy())


def run_case(name: str, params: dict[str, str] | None = None) -> dict[str, Any]:
    """The outputs (:func:`_digest` of every array) and the comparable metadata of one
    case (``params``: the detector's parameters in place of the case's own)."""
    detector_name, case_params, _, _, _, _, calibrate_s, sizes = CASES[name]
    array, block = _log(name)
    detector = make_detector(detector_name, case_params if params is None else params)
    detector.fit(block.mask(block.t_s() < calibrate_s), array)
    outputs: list[dict[str, DetectionBlock]] = []
    start, turn = 0, 0
    while start < len(block):  # uneven block cuts, cycling through ``sizes``
        stop = min(len(block), start + sizes[turn % len(sizes)])
        outputs.append(detector.process(block.slice(start, stop)))
        start, turn = stop, turn + 1
    outputs.append(detector.flush())
    record: dict[str, Any] = {}
    for sensor_type in sorted(outputs[0]):
        joined = DetectionBlock.concatenate([o[sensor_type] for o in outputs if sensor_type in o])
        record[sensor_type] = {
            f: None if getattr(joined, f) is None else _digest(getattr(joined, f)) for f in FIELDS
        }
    # through JSON, as recorded (tuples become lists, numpy scalars numbers)
    metadata = json.loads(json.dumps(detector.metadata(), default=str))
    return {"outputs": record, "metadata": comparable_metadata(without_added_params(metadata))}


def assert_outputs_match(name: str, got: dict[str, Any], want: dict[str, Any]) -> None:
    assert sorted(got) == sorted(want), name
    for sensor_type in want:
        for field in FIELDS:
            g, w = got[sensor_type][field], want[sensor_type][field]
            where = f"{name} {sensor_type}.{field}"
            if w is None:
                assert g is None, where
                continue
            assert (g["dtype"], g["shape"]) == (w["dtype"], w["shape"]), where
            if "sha256" in w:
                assert g["sha256"] == w["sha256"], f"{where}: values differ"
            else:
                assert_fingerprint_close(g["fingerprint"], w["fingerprint"], RTOL, where)


#: the cases costing over a second of CPU each run only with ``-m slow`` (CI runs both)
SLOW = (
    "bank-marg",
    "cnn-map-wearable12",
    "pca-parity-conical6",
    "pca-parity-wearable12",
    "woa-mvmd-glt-tuned",
)


@pytest.mark.parametrize(
    "name", [pytest.param(n, marks=pytest.mark.slow) if n in SLOW else n for n in sorted(CASES)]
)
def test_outputs_identical_to_the_single_module_code(name: str) -> None:
    recorded = json.loads(RECORD.read_text())["cases"][name]
    got = run_case(name)
    assert_outputs_match(name, got["outputs"], recorded["outputs"])
    assert_tree_close(got["metadata"], recorded["metadata"], RTOL, f"{name} metadata")


def test_an_added_param_is_compared_unless_it_keeps_the_recorded_behaviour() -> None:
    per_sample = {"detector": "x", "params": {"alpha": 0.01, "false_alarms_per_hour": 0.0}}
    assert without_added_params(per_sample)["params"] == {"alpha": 0.01}
    budget = {"detector": "x", "params": {"alpha": 0.01, "false_alarms_per_hour": 1.0}}
    assert without_added_params(budget) == budget


def _record() -> None:
    cases = {name: run_case(name) for name in sorted(CASES)}
    RECORD.write_text(json.dumps({"cases": cases}, indent=1, sort_keys=True) + "\n")


if __name__ == "__main__":
    _record()
