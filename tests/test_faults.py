"""Tests of imufdi_cli.faults: models, grammar, streaming injection, ground truth."""

from __future__ import annotations

import hashlib
import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose, assert_array_equal

from imufdi_cli import mcapio
from imufdi_cli.array import ArrayConfig
from imufdi_cli.errors import EXIT_USAGE, FaultSpecError, TruthError
from imufdi_cli.faults import (
    METADATA_NAME,
    MODELS,
    TRUTH_TOPIC,
    Fault,
    FaultInjector,
    active_mask,
    fault_from_table,
    faults_from_metadata,
    inject_file,
    load_fault_file,
    parse_fault_spec,
)
from imufdi_cli.log import ImuBlock, iter_blocks

DEG = math.pi / 180.0
G = 9.80665
RATE_HZ = 100.0
T0_NS = 1_700_000_000_123_456_789  # realistic epoch stamp: checks int64 arithmetic


@pytest.fixture
def array() -> ArrayConfig:
    return ArrayConfig.co_aligned(4, RATE_HZ, sensors=("gyro", "accel", "mag"))


def make_block(n: int, n_imus: int = 4, seed: int = 0) -> ImuBlock:
    rng = np.random.default_rng(seed)
    t_ns = T0_NS + np.arange(n, dtype=np.int64) * 10_000_000
    return ImuBlock(
        t_ns=t_ns,
        gyro=rng.normal(0.0, 0.01, (n, n_imus, 3)),
        accel=rng.normal(0.0, 0.1, (n, n_imus, 3)) + np.array([0.0, 0.0, G]),
        mag=rng.normal(0.0, 1e-7, (n, n_imus, 3)) + np.array([2e-5, 0.0, 4e-5]),
    )


def rel_s(block: ImuBlock) -> np.ndarray:
    return (block.t_ns - T0_NS) * 1e-9


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


# --- models: exact effects ----------------------------------------------------------------


def _inject(array: ArrayConfig, specs: list[str], block: ImuBlock, seed: int = 0) -> ImuBlock:
    faults = [parse_fault_spec(s, array) for s in specs]
    return FaultInjector(faults, array, seed=seed, t0_ns=T0_NS).apply_block(block)


def test_step_exact(array: ArrayConfig) -> None:
    block = make_block(1000)
    out = _inject(array, ["step:imu0.gyro.x,at=2.5s,until=7s,amp=0.9deg/s"], block)
    t = rel_s(block)
    expected = np.where((t >= 2.5) & (t < 7.0), 0.9 * DEG, 0.0)
    assert_allclose(out.gyro[:, 0, 0] - block.gyro[:, 0, 0], expected, atol=1e-12, rtol=0)
    # nothing else touched
    untouched = np.ones(block.gyro.shape, bool)
    untouched[:, 0, 0] = False
    assert_array_equal(out.gyro[untouched], block.gyro[untouched])
    assert_array_equal(out.accel, block.accel)
    assert_array_equal(out.mag, block.mag)


def test_drift_exact(array: ArrayConfig) -> None:
    block = make_block(1000)
    out = _inject(array, ["drift:imu1.accel,at=3s,until=8s,rate=0.01g/s"], block)
    t = rel_s(block)
    ramp = np.where((t >= 3.0) & (t < 8.0), 0.01 * G * (t - 3.0), 0.0)
    assert_allclose(
        out.accel[:, 1, :] - block.accel[:, 1, :], ramp[:, None] * np.ones(3), atol=1e-12, rtol=0
    )


def test_stuck_exact(array: ArrayConfig) -> None:
    block = make_block(600)
    out = _inject(array, ["stuck:imu2.gyro.y,at=2s,until=4s"], block)
    t = rel_s(block)
    window = (t >= 2.0) & (t < 4.0)
    last_before = np.flatnonzero(t < 2.0)[-1]
    assert_array_equal(out.gyro[window, 2, 1], block.gyro[last_before, 2, 1])
    assert_array_equal(out.gyro[~window, 2, 1], block.gyro[~window, 2, 1])


def test_stuck_from_log_start_freezes_first_sample(array: ArrayConfig) -> None:
    block = make_block(50)
    out = _inject(array, ["stuck:imu0.mag"], block)
    assert_array_equal(out.mag[:, 0, :], np.broadcast_to(block.mag[0, 0, :], (50, 3)))


def test_scale_exact(array: ArrayConfig) -> None:
    block = make_block(500)
    out = _inject(array, ["scale:imu3.accel.z,at=1s,factor=1.02"], block)
    t = rel_s(block)
    expected = np.where(t >= 1.0, 0.02 * block.accel[:, 3, 2], 0.0)
    assert_allclose(out.accel[:, 3, 2] - block.accel[:, 3, 2], expected, atol=1e-12, rtol=0)


def test_faults_on_same_sensor_compose_in_order(array: ArrayConfig) -> None:
    block = make_block(300)
    out = _inject(array, ["scale:imu0.gyro.x,factor=2", "step:imu0.gyro.x,at=1s,amp=1rad/s"], block)
    t = rel_s(block)
    assert_allclose(out.gyro[:, 0, 0], 2 * block.gyro[:, 0, 0] + (t >= 1.0), atol=1e-12)


# --- models: statistics ---------------------------------------------------------------------


@pytest.mark.slow
def test_noise_growth_sigma_ratio() -> None:
    sigma0 = 0.02
    n = 200_000
    array = ArrayConfig.co_aligned(2, noise={"accel": sigma0})
    rng = np.random.default_rng(5)
    t_ns = T0_NS + np.arange(n, dtype=np.int64) * 10_000_000
    accel = rng.normal(0.0, sigma0, (n, 2, 3))
    block = ImuBlock(t_ns=t_ns, accel=accel)
    out = _inject(array, ["noise:imu0.accel.x,at=100s,factor=3"], block, seed=11)
    t = rel_s(block)
    ratio = out.accel[t >= 100, 0, 0].std() / accel[t >= 100, 0, 0].std()
    assert abs(ratio / 3.0 - 1.0) < 0.05
    assert_array_equal(out.accel[t < 100, 0, 0], accel[t < 100, 0, 0])


def test_noise_added_sigma() -> None:
    array = ArrayConfig.co_aligned(1)
    block = ImuBlock(t_ns=np.arange(40_000) * 10_000_000, gyro=np.zeros((40_000, 1, 3)))
    faults = [parse_fault_spec("noise:imu0.gyro.z,sigma=0.5deg/s", array)]
    out = FaultInjector(faults, array, seed=3, t0_ns=0).apply_block(block)
    added = out.gyro[:, 0, 2]
    # sample std of 40000 normals: relative standard error 1/sqrt(2N) = 0.35 %
    assert abs(added.std() / (0.5 * DEG) - 1.0) < 0.02
    assert abs(added.mean()) < 4 * 0.5 * DEG / math.sqrt(40_000)


def test_spikes_rate_and_amplitude() -> None:
    array = ArrayConfig.co_aligned(1)
    n, rate = 100_000, 2.0  # 1000 s at 100 Hz
    block = ImuBlock(t_ns=np.arange(n) * 10_000_000, gyro=np.zeros((n, 1, 3)))
    faults = [parse_fault_spec(f"spikes:imu0.gyro,rate={rate}Hz,amp=1deg/s", array)]
    out = FaultInjector(faults, array, seed=9, t0_ns=0).apply_block(block).gyro[:, 0, :]
    assert set(np.unique(np.abs(out))) <= {0.0, DEG}
    counts = np.count_nonzero(out, axis=0)
    p = -math.expm1(-rate * 0.01)
    expected = n * p  # width 1: one faulty sample per event
    assert np.all(np.abs(counts - expected) < 4 * math.sqrt(expected * (1 - p)))
    positive = np.count_nonzero(out > 0)
    assert abs(positive / counts.sum() - 0.5) < 4 * 0.5 / math.sqrt(counts.sum())


def test_spikes_width() -> None:
    array = ArrayConfig.co_aligned(1)
    n = 20_000
    block = ImuBlock(t_ns=np.arange(n) * 10_000_000, gyro=np.zeros((n, 1, 3)))
    faults = [parse_fault_spec("spikes:imu0.gyro.x,rate=0.5Hz,amp=1rad/s,width=5", array)]
    out = FaultInjector(faults, array, seed=2, t0_ns=0).apply_block(block).gyro[:, 0, 0]
    on = out != 0
    starts = np.flatnonzero(on & ~np.concatenate([[False], on[:-1]]))
    ends = np.flatnonzero(on & ~np.concatenate([on[1:], [False]]))
    lengths = ends - starts + 1
    assert starts.size > 50
    assert np.all(lengths[ends < n - 1] >= 5)  # bursts may merge, never shorter than width
    assert_array_equal(np.abs(out[on]), 1.0)


# --- determinism and streaming -------------------------------------------------------------

_MIXED = [
    "noise:imu0.gyro.x,at=0.3s,until=4s,sigma=0.2deg/s",
    "spikes:imu1.gyro,at=0.5s,rate=20Hz,amp=1deg/s,width=3",
    "stuck:imu2.accel.z,at=1.05s,until=3s",
    "drift:imu3.mag.y,at=0.2s,rate=1uT/s",
    "step:imu0.gyro.x,at=1s,amp=0.1rad/s",
]


@pytest.mark.parametrize("block_size", [1, 7, 64, 333])
def test_block_splits_do_not_change_output(array: ArrayConfig, block_size: int) -> None:
    block = make_block(500)
    faults = [parse_fault_spec(s, array) for s in _MIXED]
    whole = FaultInjector(faults, array, seed=42, t0_ns=T0_NS).apply_block(block)
    injector = FaultInjector(faults, array, seed=42, t0_ns=T0_NS)
    pieces = ImuBlock.concatenate(injector.apply_block(b) for b in iter_blocks(block, block_size))
    for name in ("gyro", "accel", "mag"):
        assert_array_equal(getattr(pieces, name), getattr(whole, name))


def test_seed_determinism(array: ArrayConfig) -> None:
    block = make_block(300)
    faults = [parse_fault_spec(s, array) for s in _MIXED]
    a = FaultInjector(faults, array, seed=1, t0_ns=T0_NS).apply_block(block)
    b = FaultInjector(faults, array, seed=1, t0_ns=T0_NS).apply_block(block)
    c = FaultInjector(faults, array, seed=2, t0_ns=T0_NS).apply_block(block)
    assert_array_equal(a.gyro, b.gyro)
    assert not np.array_equal(a.gyro, c.gyro)


def test_apply_does_not_modify_input(array: ArrayConfig) -> None:
    block = make_block(200)
    before = block.copy()
    _inject(array, _MIXED, block)
    assert_array_equal(block.gyro, before.gyro)
    assert_array_equal(block.accel, before.accel)


# --- ground truth ----------------------------------------------------------------------------


def test_active_mask_hand_made(array: ArrayConfig) -> None:
    faults = [
        parse_fault_spec("step:imu0.gyro.x,at=0.02s,until=0.04s,amp=1", array),
        parse_fault_spec("stuck:imu1.gyro,at=0.03s", array),
        parse_fault_spec("step:imu0.accel.x,at=0s,amp=1", array),  # other type: ignored
    ]
    t0 = 1000
    t_ns = t0 + np.arange(6) * 10_000_000  # 0, 10, ..., 50 ms
    ids = ["imu0.gyro.x", "imu0.gyro.y", "imu1.gyro.x", "imu1.gyro.z"]
    expected = np.array(
        [
            [0, 0, 0, 0],
            [0, 0, 0, 0],
            [1, 0, 0, 0],  # 20 ms: step starts (inclusive)
            [1, 0, 1, 1],  # 30 ms: stuck starts
            [0, 0, 1, 1],  # 40 ms: step ended (exclusive)
            [0, 0, 1, 1],
        ],
        dtype=bool,
    )
    assert_array_equal(active_mask(faults, ids, t_ns, t0), expected)
    assert active_mask([], ids, t_ns, t0).shape == (6, 4)


def test_truth_events_and_metadata_round_trip(array: ArrayConfig) -> None:
    faults = [
        parse_fault_spec("drift:imu1.accel.z,at=3s,until=8s,rate=0.01g/s", array),
        parse_fault_spec("step:imu0.gyro.x,at=2.5s,amp=0.9deg/s,id=bias", array),
    ]
    injector = FaultInjector(faults, array, seed=7, t0_ns=T0_NS)
    assert [f.id for f in injector.faults] == ["f0", "bias"]
    events = injector.truth_events()
    assert [(e["event"], e["fault_id"]) for e in events] == [
        ("start", "bias"),
        ("start", "f0"),
        ("end", "f0"),
    ]
    assert events[0]["t_ns"] == T0_NS + 2_500_000_000
    assert events[2]["t_ns"] == T0_NS + 8_000_000_000
    json.dumps(events)
    meta = injector.metadata()
    record = json.loads(meta["json"])
    assert record["seed"] == 7 and record["t0_ns"] == T0_NS
    assert faults_from_metadata(meta) == injector.faults


def test_previous_faults_are_kept_and_ids_unique(array: ArrayConfig) -> None:
    first = FaultInjector(
        [parse_fault_spec("step:imu0.gyro.x,at=1s,amp=1deg/s", array)],
        array,
        seed=1,
        t0_ns=0,
    )
    second = FaultInjector(
        [parse_fault_spec("stuck:imu1.gyro.x,at=2s", array)],
        array,
        seed=2,
        t0_ns=0,
        previous_metadata=first.metadata(),
    )
    assert [f.id for f in second.faults] == ["f1"]
    every = faults_from_metadata(second.metadata())
    assert [(f.id, f.model) for f in every] == [("f0", "step"), ("f1", "stuck")]
    record = json.loads(second.metadata()["json"])
    assert record["previous"][0]["seed"] == 1
    with pytest.raises(FaultSpecError, match="id 'f0' is already used"):
        FaultInjector(
            [parse_fault_spec("stuck:imu1.gyro.x,at=2s,id=f0", array)],
            array,
            seed=2,
            t0_ns=0,
            previous_metadata=first.metadata(),
        )


def test_bad_metadata_is_truth_error() -> None:
    with pytest.raises(TruthError):
        faults_from_metadata({"json": "not json"})
    with pytest.raises(TruthError):
        faults_from_metadata({"json": '{"faults": [{"model": "step"}]}'})
    with pytest.raises(TruthError):
        faults_from_metadata({})


def test_non_finite_values_rejected(array: ArrayConfig) -> None:
    with pytest.raises(FaultSpecError, match="amp: '1e999deg/s' is not a finite number"):
        parse_fault_spec("step:imu0.gyro.x,amp=1e999deg/s", array)
    with pytest.raises(FaultSpecError, match="at: inf is not a finite number"):
        fault_from_table(
            {"model": "step", "sensor": "imu0.gyro.x", "at": math.inf, "amp": 1.0},
            array,
            where="t",
        )


def test_apply_leaves_unfaulted_streams_and_empty_blocks(array: ArrayConfig) -> None:
    injector = FaultInjector(
        [parse_fault_spec("step:imu1.gyro.y,amp=1", array)], array, seed=0, t0_ns=0
    )
    values = np.arange(12.0).reshape(4, 3)
    t_ns = np.arange(4) * 10
    assert_array_equal(injector.apply(0, "gyro", t_ns, values), values)
    assert_array_equal(injector.apply(1, "accel", t_ns, values), values)
    assert injector.apply(1, "gyro", t_ns[:0], values[:0]).shape == (0, 3)
    assert_array_equal(injector.apply(1, "gyro", t_ns, values), values + np.array([0.0, 1.0, 0.0]))
    assert injector.affects(1, "gyro") and not injector.affects(1, "accel")


# --- inject_file: MCAP in, MCAP out --------------------------------------------------------

needs_mcapio = pytest.mark.skipif(
    not all(hasattr(mcapio, n) for n in ("write_array", "read_array", "patch_imu")),
    reason="imufdi_cli.mcapio does not export its API yet",
)


def sha256(path) -> str:
    with open(path, "rb") as handle:
        return hashlib.sha256(handle.read()).hexdigest()


@pytest.fixture
def log_file(tmp_path):
    array = ArrayConfig.co_aligned(3, RATE_HZ, noise={"gyro": 0.01})
    block = make_block(500, n_imus=3)
    block.mag = None
    path = tmp_path / "clean.mcap"
    mcapio.write_array(str(path), array, block)
    return path, array, block


def _messages_by_topic(path) -> dict[str, list[tuple[int, bytes]]]:
    out: dict[str, list[tuple[int, bytes]]] = {}
    with mcapio.McapSource(str(path)) as source:
        for batch in source.batches():
            for i in range(len(batch)):
                topic = source.channels[int(batch.channel_id[i])].topic
                out.setdefault(topic, []).append((int(batch.log_time[i]), batch.payload(i)))
    return out


_FILE_SPECS = [
    "step:imu0.gyro.x,at=1s,until=3s,amp=0.9deg/s",
    "noise:imu2.accel,at=0.5s,factor=3,sigma0=0.1m/s^2",
    "spikes:imu2.gyro.z,rate=5Hz,amp=1deg/s",
]


@needs_mcapio
def test_inject_file_values_truth_and_metadata(tmp_path, log_file) -> None:
    path, array, block = log_file
    digest = sha256(path)
    out = tmp_path / "faulty.mcap"
    result = inject_file(str(path), str(out), _FILE_SPECS, [], seed=5)
    assert sha256(path) == digest  # input untouched
    assert result.t0_ns == T0_NS and result.truth_messages == 4
    assert result.imu_topics == ["/imu0/data_raw", "/imu1/data_raw", "/imu2/data_raw"]
    _, faulty = mcapio.read_array(str(out))
    faults = [parse_fault_spec(s, array) for s in _FILE_SPECS]
    expected = FaultInjector(faults, array, seed=5, t0_ns=T0_NS).apply_block(block)
    assert_array_equal(faulty.gyro, expected.gyro)
    assert_array_equal(faulty.accel, expected.accel)
    # unfaulted IMU messages are byte-identical
    before, after = _messages_by_topic(path), _messages_by_topic(out)
    assert after["/imu1/data_raw"] == before["/imu1/data_raw"]
    assert after["/imu0/data_raw"] != before["/imu0/data_raw"]
    truth = mcapio.read_json_topic(str(out), TRUTH_TOPIC)
    assert [(t, e["event"], e["fault_id"]) for t, e in truth] == [
        (T0_NS, "start", "f2"),
        (T0_NS + 500_000_000, "start", "f1"),
        (T0_NS + 1_000_000_000, "start", "f0"),
        (T0_NS + 3_000_000_000, "end", "f0"),
    ]
    with mcapio.McapSource(str(out)) as source:
        meta = source.metadata
    assert "imufdi.array" in meta
    recorded = faults_from_metadata(meta[METADATA_NAME])
    assert [f.spec for f in recorded] == _FILE_SPECS
    assert json.loads(meta[METADATA_NAME]["json"])["seed"] == 5


@needs_mcapio
def test_inject_file_deterministic_bytes(tmp_path, log_file) -> None:
    path, _, _ = log_file
    a, b, c = tmp_path / "a.mcap", tmp_path / "b.mcap", tmp_path / "c.mcap"
    inject_file(str(path), str(a), _FILE_SPECS, [], seed=1)
    inject_file(str(path), str(b), _FILE_SPECS, [], seed=1)
    inject_file(str(path), str(c), _FILE_SPECS, [], seed=2)
    assert sha256(a) == sha256(b) != sha256(c)


@needs_mcapio
@pytest.mark.parametrize(
    ("specs", "message"),
    [
        (["step:imu3.gyro.x,amp=1deg/s"], "IMU index 3 is past the array"),
        (["step:imu0.gyro.x,at=9s,amp=1deg/s"], "is after the log ends"),
        (["step:imu0.gyro.x,amp=1deg/s", "stuck:imu0.gyro.q"], "axis 'q'"),
        ([], "needs at least one --fault"),
    ],
)
def test_inject_file_validates_before_writing(tmp_path, log_file, specs, message) -> None:
    path, _, _ = log_file
    out = tmp_path / "never.mcap"
    with pytest.raises(FaultSpecError, match=message):
        inject_file(str(path), str(out), specs, [], seed=0)
    assert list(tmp_path.iterdir()) == [path]


@needs_mcapio
def test_inject_twice_keeps_previous_truth(tmp_path, log_file) -> None:
    path, _, _ = log_file
    once, twice = tmp_path / "once.mcap", tmp_path / "twice.mcap"
    toml = tmp_path / "more.toml"
    toml.write_text('[[fault]]\nmodel = "stuck"\nsensor = "imu1.gyro"\nat = "2s"\n')
    inject_file(str(path), str(once), _FILE_SPECS[:1], [], seed=1)
    result = inject_file(str(once), str(twice), [], [str(toml)], seed=2)
    assert [f.id for f in result.previous_faults] == ["f0"]
    assert [f.id for f in result.faults] == ["f1"]
    truth = mcapio.read_json_topic(str(twice), TRUTH_TOPIC)
    assert sorted(e["fault_id"] for _, e in truth) == ["f0", "f0", "f1"]
    with mcapio.McapSource(str(twice)) as source:
        recorded = faults_from_metadata(source.metadata[METADATA_NAME])
    assert [(f.id, f.model) for f in recorded] == [("f0", "step"), ("f1", "stuck")]


@needs_mcapio
def test_inject_refuses_to_overwrite_input(log_file) -> None:
    path, _, _ = log_file
    with pytest.raises(Exception, match="is the input file") as info:
        inject_file(str(path), str(path), _FILE_SPECS, [], seed=0)
    assert info.value.exit_code == 2  # type: ignore[attr-defined]


@needs_mcapio
def test_inject_from_stdin_matches_file_input(tmp_path, log_file, monkeypatch) -> None:
    import io
    import sys

    path, _, _ = log_file
    from_file, from_stdin = tmp_path / "file.mcap", tmp_path / "stdin.mcap"
    inject_file(str(path), str(from_file), _FILE_SPECS, [], seed=3)
    monkeypatch.setattr(sys, "stdin", io.TextIOWrapper(io.BytesIO(path.read_bytes())))
    inject_file("-", str(from_stdin), _FILE_SPECS, [], seed=3)
    assert sha256(from_file) == sha256(from_stdin)


@needs_mcapio
def test_inject_magnetometer(tmp_path) -> None:
    array = ArrayConfig.co_aligned(2, RATE_HZ, sensors=("gyro", "accel", "mag"))
    block = make_block(300, n_imus=2)
    path, out = tmp_path / "mag.mcap", tmp_path / "mag-faulty.mcap"
    mcapio.write_array(str(path), array, block)
    spec = "drift:imu1.mag,at=1s,rate=2uT/s"
    inject_file(str(path), str(out), [spec], [], seed=0)
    _, faulty = mcapio.read_array(str(out))
    t = rel_s(block)
    ramp = np.where(t >= 1.0, 2e-6 * (t - 1.0), 0.0)
    assert_allclose(
        faulty.mag[:, 1, :] - block.mag[:, 1, :], ramp[:, None] * np.ones(3), atol=1e-15
    )
    assert_array_equal(faulty.mag[:, 0, :], block.mag[:, 0, :])
    assert_array_equal(faulty.gyro, block.gyro)


@needs_mcapio
def test_inject_fault_on_missing_topic(tmp_path, log_file) -> None:
    path, _, _ = log_file
    # a log whose recorded array claims magnetometers it carries no topic for
    mag_array = ArrayConfig.co_aligned(3, RATE_HZ, sensors=("gyro", "accel", "mag"))
    no_mag = tmp_path / "nomag.mcap"
    with mcapio.McapSource(str(path)) as source, mcapio.McapWriter(str(no_mag)) as writer:
        writer.copy_channels(source.channels)
        writer.add_metadata("imufdi.array", {"json": mag_array.to_json()})
        for batch in source.batches():
            writer.add_batch(batch)
    out = tmp_path / "never.mcap"
    with pytest.raises(FaultSpecError, match="no mag topic for imu1"):
        inject_file(str(no_mag), str(out), ["step:imu1.mag.x,amp=1uT"], [], seed=0)
    assert not out.exists()
