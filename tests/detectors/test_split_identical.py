"""bank, cnn-map, pca-parity and woa-mvmd-glt give the outputs recorded before their package split.

The two pca-parity cases were recorded on main de59088 (single module) before
``detectors/pca_parity.py`` became a package.

``detectors/bank.py``, ``detectors/cnn_map.py`` and ``detectors/woa_mvmd_glt.py`` were split
into packages by concern with behaviour unchanged. The records in
``data/split_identical.json`` were made with the single-module code (first on commit
1804bff; last on main dae5119, still single-module, after main's noise-glr change moved
cnn-map's input test and with one BLAS thread per case, which moved woa-mvmd-glt's
fixed-clip case; the package split matched every record made on the same code; the two
woa-mvmd-glt metadata hashes were re-recorded when the detector gained the
``noise_spread`` and ``u_best`` settings, which its metadata lists, with every output array
unchanged): each
detector runs on a fixed seeded simulated log with injected faults, streamed in uneven
blocks, and every array of every :class:`DetectionBlock` (statistic, threshold, alarm,
isolated, amplitude, scores, isolated_set, amplitudes) is hashed (SHA-256 of its bytes) and
fingerprinted, as is the metadata JSON. The cnn-map case's metadata hash was re-recorded
once since: ``calibration_motion_ratio`` changed on purpose (the
motion check's noise level), its outputs and every other metadata field kept their bytes.
The two woa-mvmd-glt metadata hashes were re-recorded once more when ``u_best=lowest``
became the default (the metadata names the rule); every output array kept its bytes.

On the machine and numpy version of the record the hashes must match **byte for byte**. On
another CPU or numpy a different summation order may move the last bits, so there the
fingerprints are compared instead: NaN count exact, (sum, sum of squares, sin-weighted sum)
to 1e-9 of the sum |x| — any change of a row beyond rounding shows.

Each case runs with one BLAS thread (as the CLI runs): the thread count changes the
summation order of matrix products, and so the last bits. In the test process when its
BLAS was pinned to one thread before numpy loaded (``tests/conftest.py``, the
``one_blas_thread`` fixture), else in a fresh interpreter with one thread.

Re-record (only for a deliberate change of outputs, saying why in the commit):
``PYTHONPATH=. python tests/detectors/test_split_identical.py``.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from imufdi_cli.detectors import make_detector
from imufdi_cli.detectors.base import DetectionBlock
from imufdi_cli.faults import FaultInjector, parse_fault_spec
from imufdi_cli.log import ImuBlock
from imufdi_cli.simulate import preset, simulate_block

RECORD = Path(__file__).parent / "data" / "split_identical.json"
ROOT = Path(__file__).resolve().parents[2]
#: one BLAS thread, as the CLI runs (imufdi_cli.cli): a different thread count changes the
#: summation order of matrix products and so the last bits of the outputs
THREADS = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
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
    array = np.ascontiguousarray(values)
    raw = array.astype(np.float64).ravel()
    x = np.where(np.isnan(raw), 0.0, raw)
    weights = np.sin(0.37 * np.arange(x.size) + 1.0)
    return {
        "dtype": str(array.dtype),
        "shape": list(array.shape),
        "sha256": hashlib.sha256(array.tobytes()).hexdigest(),
        "fingerprint": [
            float(np.isnan(raw).sum()),
            float(x.sum()),
            float((x * x).sum()),
            float((x * weights).sum()),
            float(np.abs(x).sum()),
        ],
    }


#: metadata keys that change between runs of the same code: tuning wall time, and whether
#: the tuning came from the in-process cache of an earlier identical fit.
VOLATILE = frozenset({"seconds", "reused"})


def _stable(value: Any) -> Any:
    """``value`` (metadata) without the :data:`VOLATILE` keys, at any depth."""
    if isinstance(value, dict):
        return {k: _stable(v) for k, v in value.items() if k not in VOLATILE}
    if isinstance(value, list | tuple):
        return [_stable(v) for v in value]
    return value


def _log(name: str) -> tuple[Any, ImuBlock]:
    _, _, preset_name, seed, duration, faults, _, _ = CASES[name]
    array, clean = simulate_block(preset(preset_name, seed=seed, duration=duration))
    specs = [parse_fault_spec(s, array) for s in faults]
    injector = FaultInjector(specs, array, seed=seed, t0_ns=int(clean.t_ns[0]))
    return array, injector.apply_block(clean.copy())


def run_case(name: str) -> dict[str, Any]:
    """Digests of every output array and of the metadata of one case."""
    detector_name, params, _, _, _, _, calibrate_s, sizes = CASES[name]
    array, block = _log(name)
    detector = make_detector(detector_name, params)
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
    meta = json.dumps(_stable(detector.metadata()), sort_keys=True, default=str)
    record["metadata_sha256"] = hashlib.sha256(meta.encode()).hexdigest()
    return record


def _environment() -> dict[str, str]:
    return {"numpy": np.__version__, "machine": platform.machine(), "python": sys.version[:4]}


def _assert_same(name: str, got: dict[str, Any], want: dict[str, Any], exact: bool) -> None:
    assert sorted(got) == sorted(want), name
    if exact:
        assert got["metadata_sha256"] == want["metadata_sha256"], f"{name}: metadata"
    for sensor_type in (k for k in want if k != "metadata_sha256"):
        for field in FIELDS:
            g, w = got[sensor_type][field], want[sensor_type][field]
            where = f"{name} {sensor_type}.{field}"
            if w is None:
                assert g is None, where
                continue
            assert (g["dtype"], g["shape"]) == (w["dtype"], w["shape"]), where
            if exact:
                assert g["sha256"] == w["sha256"], f"{where}: bytes differ"
            else:
                assert g["fingerprint"][0] == w["fingerprint"][0], f"{where}: NaN count"
                scale = max(w["fingerprint"][4], 1.0)
                np.testing.assert_allclose(
                    g["fingerprint"][1:4], w["fingerprint"][1:4], rtol=0, atol=1e-9 * scale
                )


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
def test_outputs_identical_to_the_single_module_code(name: str, one_blas_thread: bool) -> None:
    recorded = json.loads(RECORD.read_text())
    exact = recorded["environment"] == _environment()
    got = run_case(name) if one_blas_thread else run_isolated(name)
    _assert_same(name, got, recorded["cases"][name], exact)


def run_isolated(name: str) -> dict[str, Any]:
    """:func:`run_case` in a fresh interpreter with one BLAS thread (:data:`THREADS`), so
    that neither the test process's BLAS set-up nor earlier tests touch the bits."""
    env = {**os.environ, **THREADS}
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    done = subprocess.run(
        [sys.executable, __file__, "--case", name],
        capture_output=True,
        text=True,
        env=env,
        cwd=ROOT,
    )
    assert done.returncode == 0, done.stderr
    record: dict[str, Any] = json.loads(done.stdout)
    return record


def _record() -> None:
    cases = {name: run_isolated(name) for name in sorted(CASES)}
    text = json.dumps({"environment": _environment(), "cases": cases}, indent=1, sort_keys=True)
    RECORD.write_text(text + "\n")


if __name__ == "__main__":
    if sys.argv[1:2] == ["--case"]:
        print(json.dumps(run_case(sys.argv[2])))
    else:
        _record()
