"""Tests of imufdi_cli.faults.spec: the fault grammar and fault files."""

from __future__ import annotations

import json
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from imufdi_cli.array import ArrayConfig
from imufdi_cli.errors import EXIT_USAGE, FaultSpecError
from imufdi_cli.faults import (
    MODELS,
    Fault,
    FaultInjector,
    fault_from_table,
    load_fault_file,
    parse_fault_spec,
)
from tests.faults.conftest import DEG, G

# --- grammar -----------------------------------------------------------------------------


def test_parse_step_in_si(array: ArrayConfig) -> None:
    fault = parse_fault_spec("step:imu0.gyro.x,at=2.5s,amp=0.9deg/s", array)
    assert fault.model == "step"
    assert fault.sensors == ["imu0.gyro.x"]
    assert fault.at_s == 2.5 and fault.until_s is None
    assert_allclose(fault.params["amp"], 0.9 * DEG, rtol=1e-15)
    assert fault.spec == "step:imu0.gyro.x,at=2.5s,amp=0.9deg/s"


def test_parse_drift_triad_and_until(array: ArrayConfig) -> None:
    fault = parse_fault_spec("drift:imu1.accel,at=3s,until=8s,rate=0.01g/s", array)
    assert fault.sensors == ["imu1.accel.x", "imu1.accel.y", "imu1.accel.z"]
    assert (fault.at_s, fault.until_s) == (3.0, 8.0)
    assert_allclose(fault.params["rate"], 0.01 * G, rtol=1e-15)


def test_parse_noise_factor_needs_sigma0(array: ArrayConfig) -> None:
    with pytest.raises(FaultSpecError, match="sigma0"):
        parse_fault_spec("noise:imu0.accel.x,at=12s,until=18s,factor=3", array)
    fault = parse_fault_spec("noise:imu0.accel.x,at=12s,factor=3,sigma0=0.02m/s^2", array)
    assert_allclose(fault.params["sigma"], 0.02 * math.sqrt(8.0), rtol=1e-15)
    noisy = ArrayConfig.co_aligned(2, noise={"accel": 0.05})
    fault = parse_fault_spec("noise:imu1.accel.x,factor=2", noisy)
    assert_allclose(fault.params["sigma"], 0.05 * math.sqrt(3.0), rtol=1e-15)
    fault = parse_fault_spec("noise:imu1.accel.x,sigma=10mg", noisy)
    assert_allclose(fault.params["sigma"], 0.01 * G, rtol=1e-15)


def test_parse_scale_ppm_spikes_duration(array: ArrayConfig) -> None:
    assert_allclose(
        parse_fault_spec("scale:imu0.gyro.z,ppm=500", array).params["factor"], 1.0005, rtol=1e-15
    )
    spikes = parse_fault_spec("spikes:imu2.mag.y,at=1s,duration=2s,rate=30/min,amp=5uT", array)
    assert spikes.until_s == 3.0
    assert_allclose(spikes.params["rate"], 0.5)
    assert_allclose(spikes.params["amp"], 5e-6)
    assert spikes.params["width"] == 1.0
    assert parse_fault_spec("stuck:imu3.gyro.y,at=1s", array).params == {}


@pytest.mark.parametrize(
    ("spec", "field"),
    [
        ("bump:imu0.gyro.x,amp=1deg/s", "unknown model 'bump'; valid: drift, noise"),
        ("step:imu0.gyro.x,amp=1deg/s,slope=2", "unknown key 'slope' for step; valid: amp, at"),
        ("step:imu0.gyro.w,amp=1deg/s", "sensor: sensor 'imu0.gyro.w': axis 'w'"),
        ("step:imu0.baro.x,amp=1deg/s", "sensor: unknown sensor type 'baro'"),
        ("step:imu9.gyro.x,amp=1deg/s", "IMU index 9 is past the array (imu0..imu3)"),
        ("step:gyro.x,amp=1deg/s", "sensor: sensor 'gyro.x' is not of the form"),
        ("drift:imu0.gyro.x,at=5s,until=3s,rate=1deg/s^2", "until (3 s) must be after at"),
        ("drift:imu0.gyro.x,at=5s,until=5s,rate=1deg/s^2", "negative or zero duration"),
        ("step:imu0.gyro.x,at=1s", "step needs amp="),
        ("drift:imu0.gyro.x,at=1s", "drift needs rate="),
        ("scale:imu0.gyro.x,at=1s", "scale needs factor= or ppm="),
        ("noise:imu0.gyro.x,at=1s", "noise needs factor= or sigma="),
        ("spikes:imu0.gyro.x,rate=1Hz", "spikes needs amp="),
        ("step:imu0.accel.x,amp=0.9deg/s", "amp: '0.9deg/s' is not an acceleration"),
        ("drift:imu0.gyro.x,rate=0.9deg/s", "rate: '0.9deg/s' is not an angular acceleration"),
        ("step:imu0.gyro.x,at=2parsecs,amp=1deg/s", "unknown unit 'parsecs'"),
        ("step:imu0.gyro.x,at=-1s,amp=1deg/s", "at must be >= 0"),
        ("step:imu0.gyro.x,amp", "'amp' is not key=value"),
        ("step:imu0.gyro.x,amp=1,amp=2", "key 'amp' given twice"),
        ("imu0.gyro.x,amp=1", "expected MODEL:SENSOR"),
        ("noise:imu0.gyro.x,factor=0.5,sigma0=1deg/s", "factor must be >= 1"),
        ("spikes:imu0.gyro.x,rate=1Hz,amp=1deg/s,width=1.5", "width must be a whole number"),
        ("spikes:imu0.gyro.x,rate=0Hz,amp=1deg/s", "rate (events per second) must be > 0"),
        ("scale:imu0.gyro.x,factor=1.1,ppm=3", "give only one of factor, ppm"),
    ],
)
def test_bad_specs_name_the_field(array: ArrayConfig, spec: str, field: str) -> None:
    with pytest.raises(FaultSpecError) as info:
        parse_fault_spec(spec, array)
    message = str(info.value)
    assert field in message
    assert "\n" not in message
    assert info.value.exit_code == EXIT_USAGE == 2


def test_unknown_model_lists_all_models(array: ArrayConfig) -> None:
    with pytest.raises(FaultSpecError, match=", ".join(MODELS)):
        parse_fault_spec("bump:imu0.gyro.x,amp=1", array)


def test_imu_without_that_sensor() -> None:
    array = ArrayConfig.co_aligned(2)  # gyro + accel only
    with pytest.raises(FaultSpecError, match="imu1 has no mag"):
        parse_fault_spec("step:imu1.mag.x,amp=1uT", array)


def test_start_after_log_end_rejected_when_duration_known(array: ArrayConfig) -> None:
    fault = parse_fault_spec("step:imu0.gyro.x,at=12s,amp=1deg/s", array)
    FaultInjector([fault], array, seed=0, t0_ns=0)  # unknown duration: accepted
    with pytest.raises(FaultSpecError, match=r"at \(12 s\) is after the log ends \(10 s\)"):
        FaultInjector([fault], array, seed=0, t0_ns=0, log_duration_s=10.0)


def test_toml_file(tmp_path, array: ArrayConfig) -> None:
    path = tmp_path / "faults.toml"
    path.write_text(
        '[[fault]]\nmodel = "step"\nsensor = "imu0.gyro.x"\nat = "2.5s"\namp = "0.9deg/s"\n\n'
        '[[fault]]\nmodel = "drift"\nsensor = "imu1.accel.z"\nat = 3\nuntil = "8s"\n'
        'rate = "0.01g/s"\n'
    )
    faults = load_fault_file(path, array)
    assert [f.model for f in faults] == ["step", "drift"]
    assert faults[0].to_dict() == {
        **parse_fault_spec("step:imu0.gyro.x,at=2.5s,amp=0.9deg/s", array).to_dict(),
    }
    assert faults[1].at_s == 3.0 and faults[1].until_s == 8.0
    assert_allclose(faults[1].params["rate"], 0.01 * G)


def test_toml_errors(tmp_path, array: ArrayConfig) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text('[[fault]]\nmodel = "step"\nsensor = "imu0.gyro.x"\namp = "1g"\n')
    with pytest.raises(FaultSpecError, match=r"fault\[0\].*amp: '1g' is not an angular rate"):
        load_fault_file(bad, array)
    with pytest.raises(FaultSpecError, match="missing sensor"):
        fault_from_table({"model": "step", "amp": 1.0}, array, where="t")
    bad.write_text("[[faults]]\n")
    with pytest.raises(FaultSpecError, match="unknown top-level key 'faults'; valid: fault"):
        load_fault_file(bad, array)
    bad.write_text("[[fault]\n")
    with pytest.raises(FaultSpecError, match="not valid TOML"):
        load_fault_file(bad, array)
    with pytest.raises(FaultSpecError, match="cannot read fault file"):
        load_fault_file(tmp_path / "missing.toml", array)


_SENSORS = st.sampled_from(["imu0.gyro.x", "imu3.gyro", "imu2.accel.z", "imu1.mag.y"])


@settings(max_examples=60, deadline=None)
@given(
    sensor=_SENSORS,
    at=st.floats(0, 100, allow_nan=False),
    length=st.one_of(st.none(), st.floats(0.001, 50)),
    amp=st.floats(-1e3, 1e3, allow_nan=False),
)
def test_step_spec_round_trip(sensor: str, at: float, length: float | None, amp: float) -> None:
    array = ArrayConfig.co_aligned(4, sensors=("gyro", "accel", "mag"))
    unit = {"gyro": "rad/s", "accel": "m/s^2", "mag": "T"}[sensor.split(".")[1]]
    spec = f"step:{sensor},at={at!r}s,amp={amp!r}{unit}"
    if length is not None and at + length > at:
        spec += f",until={at + length!r}s"
    fault = parse_fault_spec(spec, array)
    assert fault.params["amp"] == amp
    assert fault.at_s == at
    assert all(s.startswith(sensor) for s in fault.sensors)
    again = Fault.from_dict(json.loads(json.dumps(fault.to_dict())))
    assert again == fault


@settings(max_examples=200, deadline=None)
@given(text=st.text(alphabet="stepdrifnoaukc:imu0123.gyroaclxyz,=sdeg/s^-+e5 ", max_size=60))
def test_parser_raises_only_fault_spec_error(text: str) -> None:
    array = ArrayConfig.co_aligned(4, sensors=("gyro", "accel", "mag"))
    try:
        parse_fault_spec(text, array)
    except FaultSpecError as err:
        assert "\n" not in str(err)
