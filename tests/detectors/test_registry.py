"""The detector registry: lazy, complete, and consistent with each class."""

from __future__ import annotations

import inspect
import subprocess
import sys

import pytest

from imufdi_cli.detectors import (
    DETECTORS,
    Detector,
    DetectorBase,
    ParameterRenamedWarning,
    detector_class,
    make_detector,
    make_detectors,
)
from imufdi_cli.errors import DetectorConfigError


@pytest.mark.parametrize("name", sorted(DETECTORS))
def test_every_entry_imports_and_matches_its_name(name: str) -> None:
    cls = detector_class(name)
    assert cls.name == name  # type: ignore[attr-defined]
    assert isinstance(make_detector(name), Detector)


def test_unknown_name_lists_the_valid_ones() -> None:
    with pytest.raises(DetectorConfigError, match=r"unknown detector 'nope'; valid: .*glt"):
        make_detector("nope")


def test_cli_help_imports_no_detector_module_and_no_scipy() -> None:
    probe = (
        "import runpy, sys\n"
        "sys.argv = ['imufdi', '--help']\n"
        "try:\n    runpy.run_module('imufdi_cli', run_name='__main__')\n"
        "except SystemExit:\n    pass\n"
        "heavy = sorted(m for m in sys.modules if m.startswith('scipy')"
        " or (m.startswith('imufdi_cli.detectors.') and m != 'imufdi_cli.detectors.base'))\n"
        "print(heavy)\n"
        "from imufdi_cli.detectors import DETECTORS, detector_class\n"  # the registry
        "classes = [detector_class(name) for name in DETECTORS]\n"  # and every detector
        "print([m for m in sys.modules if m.startswith('scipy')])\n"
    )
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert done.stdout.strip().splitlines()[-2:] == ["[]", "[]"]


@pytest.mark.parametrize("name", sorted(DETECTORS))
def test_constructor_takes_exactly_the_declared_params_with_their_defaults(name: str) -> None:
    """One interface: ``from_params`` passes every PARAMS entry as a keyword of __init__."""
    cls = detector_class(name)
    signature = inspect.signature(cls.__init__)
    arguments = {k: p for k, p in signature.parameters.items() if k != "self"}
    assert sorted(arguments) == sorted(cls.PARAMS)
    for key, spec in cls.PARAMS.items():
        assert arguments[key].default == spec.default, key
    assert cls.from_params.__func__ is DetectorBase.from_params.__func__  # type: ignore[attr-defined]


def test_the_sensor_type_parameter_has_one_name() -> None:
    with_types = {name for name in DETECTORS if "types" in detector_class(name).PARAMS}
    assert with_types == set(DETECTORS) - {"bank", "cnn-map"}  # these two pick their own
    assert not [name for name in DETECTORS if "sensors" in detector_class(name).PARAMS]


@pytest.mark.parametrize("name", ["pca-parity", "noise-glr"])
def test_old_sensors_name_is_accepted_with_a_warning(name: str) -> None:
    with pytest.warns(ParameterRenamedWarning, match=rf"{name}\.sensors is deprecated"):
        old = make_detector(name, {"sensors": "gyro"})
    assert old.sensor_types == ("gyro",)  # type: ignore[attr-defined]
    detectors, notes = make_detectors([(name, {"sensors": "accel"}), ("glt", {})])
    assert [d.name for d in detectors] == [name, "glt"]
    assert notes == [f"{name}.sensors is deprecated; use {name}.types"]
    with pytest.raises(DetectorConfigError, match="give types only"):
        make_detector(name, {"sensors": "gyro", "types": "gyro"})
    cls = detector_class(name)
    with pytest.warns(ParameterRenamedWarning, match=rf"{name}\.sensors is deprecated"):
        direct = cls(sensors="accel")  # type: ignore[call-arg]  # Python callers too
    assert direct.sensor_types == ("accel",)  # type: ignore[attr-defined]


@pytest.mark.parametrize(
    ("name", "raw", "match"),
    [
        ("bank", {"mode": "kalman"}, "valid: auto, marg, array"),
        ("cnn-map", {"activation": "relu6"}, "valid: "),
        ("ap-consistency", {"reference": "median"}, "valid: "),
        ("woa-mvmd-glt", {"window": "3"}, "must be >= "),
        ("woa-mvmd-glt", {"types": "gyro,baro"}, "valid: gyro, accel, mag"),
        ("woa-mvmd-glt", {"overlap": "50"}, "< window"),  # between parameters: __init__
        ("pca-parity", {"bogus": "1"}, r"unknown parameter pca-parity\.bogus; valid: "),
    ],
)
def test_bad_params_are_caught_by_the_one_construction_path(name, raw, match) -> None:
    with pytest.raises(DetectorConfigError, match=match):
        make_detector(name, raw)
