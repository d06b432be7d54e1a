"""The health detector: checks of each sensor axis alone (imufdi_cli.detectors.health)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from imufdi_cli.array import ArrayConfig
from imufdi_cli.detectors import make_detector
from imufdi_cli.detectors.base import NOT_ISOLABLE, DetectionBlock
from imufdi_cli.detectors.health import HealthDetector, _run_lengths
from imufdi_cli.episodes.episode import Episode, find_episodes
from imufdi_cli.errors import CalibrationError, DetectorConfigError
from imufdi_cli.log import ImuBlock

RATE = 100.0
SIGMA = 0.003  # rad/s


def _gyro_log(n: int, seed: int, n_imus: int = 1, t0_ns: int = 0) -> ImuBlock:
    """White gyro noise on a slow sinusoidal motion (the first differences see the noise)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / RATE
    motion = 0.2 * np.sin(2 * np.pi * 0.05 * t)[:, None, None] * np.ones((1, n_imus, 3))
    gyro = motion + rng.normal(0.0, SIGMA, (n, n_imus, 3))
    return ImuBlock(t_ns=t0_ns + np.round(t * 1e9).astype(np.int64), gyro=gyro)


def _fitted(block: ImuBlock, n_cal: int = 1000, n_imus: int = 1, **params) -> HealthDetector:
    detector = make_detector("health", {"types": "gyro", **params})
    assert isinstance(detector, HealthDetector)
    array = ArrayConfig.co_aligned(n_imus, RATE, sensors=("gyro",))
    detector.fit(block.mask(np.arange(len(block)) < n_cal), array)
    return detector


def _run(detector: HealthDetector, block: ImuBlock, size: int = 500) -> DetectionBlock:
    parts = [
        detector.process(
            block.mask((np.arange(len(block)) >= a) & (np.arange(len(block)) < a + size))
        )["gyro"]
        for a in range(0, len(block), size)
    ]
    return DetectionBlock.concatenate(parts)


def _episode(detector: HealthDetector, block: ImuBlock, out: DetectionBlock) -> Episode:
    """The first alarm run of ``out`` as an episode, explained by the detector."""
    start, stop = find_episodes(out.alarm, merge_gap=10)[0]
    iso = out.isolated[start:stop]
    iso = iso[iso >= 0]
    ids = detector.array.sensor_ids("gyro")  # type: ignore[union-attr]
    sensors = [ids[int(np.bincount(iso).argmax())]] if iso.size else []
    episode = Episode(
        "health",
        "gyro",
        int(block.t_ns[start]),
        int(block.t_ns[stop - 1]),
        int(block.t_ns[start]),
        int(block.t_ns[stop - 1]),
        stop - start,
        sensors,
        1.0,
    )
    episode.fits = detector.explain_episode(episode)
    return episode


def test_run_lengths_count_repeats_across_blocks():
    same = np.array([[1, 0], [1, 1], [0, 1], [1, 1]], dtype=bool)
    assert _run_lengths(same, np.array([2, 0])).tolist() == [[3, 0], [4, 1], [0, 2], [1, 3]]


def test_stuck_axis_is_detected_isolated_and_explained_as_stuck():
    block = _gyro_log(4000, seed=101)
    gyro = block.gyro.copy()  # type: ignore[union-attr]
    gyro[2500:3000, 0, 1] = gyro[2500, 0, 1]  # imu0.gyro.y frozen for 5 s
    block = ImuBlock(t_ns=block.t_ns, gyro=gyro)
    detector = _fitted(block, false_alarms="1/h")
    out = _run(detector, block)
    assert not out.alarm[:2500].any() and not out.alarm[3010:].any()
    # R repeats after the frozen sample (R from a continuous output: a few samples)
    repeats = detector.models["gyro"].repeats[1]
    assert 2 <= repeats <= 8
    assert out.alarm[2500 + repeats : 3000].all()
    assert set(out.isolated[out.alarm]) == {1}
    episode = _episode(detector, block, out)
    assert episode.fault_class == "stuck"
    assert episode.fits[0].size == gyro[2500, 0, 1]
    # the variance is gone (the episode's span ends with a healthy difference or two)
    assert episode.fits[1].model == "noise" and episode.fits[1].size < 0.05


def test_variance_growth_and_drop_are_explained_as_noise_with_their_factor():
    block = _gyro_log(6000, seed=102)
    rng = np.random.default_rng(7)
    gyro = block.gyro.copy()  # type: ignore[union-attr]
    gyro[2000:3000, 0, 2] += rng.normal(0.0, 3 * SIGMA, 1000)  # std x sqrt(10)
    motion = 0.2 * np.sin(2 * np.pi * 0.05 * np.arange(4000, 5000) / RATE)
    gyro[4000:5000, 0, 0] = motion + rng.normal(0.0, 0.1 * SIGMA, 1000)  # std x 0.1
    block = ImuBlock(t_ns=block.t_ns, gyro=gyro)
    detector = _fitted(block, false_alarms="1/h", checks="drop,growth,stuck")
    out = _run(detector, block)
    runs = find_episodes(out.alarm, merge_gap=10)
    assert len(runs) == 2
    grow = _episode(detector, block, out)
    assert grow.sensors == ["imu0.gyro.z"] and grow.fault_class == "noise"
    fit = grow.fits[0]
    assert fit.low < math.sqrt(10) < fit.high  # the interval holds the true factor
    later = DetectionBlock.concatenate([out])
    later.alarm[: runs[0][1]] = False
    drop = _episode(detector, block, later)
    assert drop.sensors == ["imu0.gyro.x"] and drop.fault_class == "noise"
    assert drop.fits[0].size < 0.3


def test_spikes_clipping_dropouts_and_gaps():
    block = _gyro_log(3000, seed=103)
    gyro = block.gyro.copy()  # type: ignore[union-attr]
    gyro[1500, 0, 0] += 40 * SIGMA  # a spike on x
    gyro[1800:1805, 0, 1] = 4.0  # clipped on y (range 4 rad/s)
    gyro[2100:2103, 0, 2] = np.nan  # dropout on z
    t = block.t_ns.copy()
    t[2500:] += 500_000_000  # a 0.5 s gap in the sample times
    block = ImuBlock(t_ns=t, gyro=gyro)
    detector = make_detector("health", {"types": "gyro", "false_alarms": "1/h"})
    array = ArrayConfig.co_aligned(1, RATE, sensors=("gyro",)).with_range({"gyro": 4.0})
    detector.fit(block.mask(np.arange(3000) < 1000), array)
    out = _run(detector, block)
    by_run = {}
    for start, stop in find_episodes(out.alarm, merge_gap=10):
        mask = np.zeros(3000, bool)
        mask[start:stop] = True
        copy = DetectionBlock.concatenate([out])
        copy.alarm &= mask
        by_run[start] = _episode(detector, block, copy)
    spike = by_run[1500]
    assert spike.fault_class == "spikes" and spike.sensors == ["imu0.gyro.x"]
    assert spike.fits[0].size == pytest.approx(40 * SIGMA, rel=0.3)  # noise of 2 samples
    clip = by_run[1800]
    assert clip.fault_class == "clipping" and clip.fits[0].size == 4.0
    drop = by_run[2100]
    assert drop.fault_class == "dropout" and drop.fits[0].size == pytest.approx(0.03)
    gap = by_run[2500]
    assert out.isolated[2500] == NOT_ISOLABLE
    assert gap.fault_class == "dropout" and gap.fits[0].size == pytest.approx(0.5, abs=0.011)
    assert set(by_run) == {1500, 1800, 2100, 2500}  # nothing else alarmed


def test_block_size_does_not_change_any_row():
    block = _gyro_log(1600, seed=104, n_imus=2)
    gyro = block.gyro.copy()  # type: ignore[union-attr]
    gyro[1100:1300, 1, 0] = gyro[1100, 1, 0]
    gyro[1400, 0, 2] += 0.2
    block = ImuBlock(t_ns=block.t_ns, gyro=gyro)
    rows = [_run(_fitted(block, n_imus=2), block, size) for size in (1600, 7, 256)]
    for other in rows[1:]:
        for field in ("statistic", "alarm", "isolated", "scores"):
            np.testing.assert_array_equal(getattr(other, field), getattr(rows[0], field))
    assert rows[0].alarm.any()


def test_budget_sets_stricter_thresholds_than_the_per_sample_test():
    block = _gyro_log(1000, seed=105)
    loose = _fitted(block).models["gyro"]
    strict = _fitted(block, false_alarms="1/h").models["gyro"]
    assert strict.level == pytest.approx(1 / 3600 / RATE / (4 * 3))
    assert loose.level == pytest.approx(0.01 / (4 * 3))
    assert strict.spike_z > loose.spike_z and strict.h_growth > loose.h_growth
    assert strict.h_drop > loose.h_drop and (strict.repeats >= loose.repeats).all()


def test_motion_inside_the_calibration_window_does_not_make_the_hover_a_variance_drop():
    """Two seconds of brisk motion in a 10 s window (the differences 4x the noise there, as
    a quadrotor's attitude changes make them): the mean of the squared differences would
    put sigma_d about 2x too high and the hover after it would read as a variance drop;
    leaving out the one-second blocks beyond twice the blocks' median keeps sigma_d within
    10 % of the noise (800 differences: 3 % of sampling error) and the hover raises nothing
    at 1/h."""
    rng = np.random.default_rng(106)
    n_cal, n = 1000, 30000
    block = _gyro_log(n, seed=106)
    gyro = block.gyro.copy()
    burst = np.zeros((n, 1, 3))
    burst[300:500] = rng.normal(0.0, 4.0 * SIGMA, (200, 1, 3))  # 2 s: 4x the differences
    gyro += burst
    moved = ImuBlock(t_ns=block.t_ns, gyro=gyro)
    detector = _fitted(moved, n_cal=n_cal, false_alarms="1/h")
    sigma_d = detector.models["gyro"].sigma_d
    assert np.all(np.abs(sigma_d / SIGMA - 1.0) < 0.1)
    d = np.diff(gyro[:n_cal, 0, :], axis=0)
    assert np.all(np.sqrt(np.mean(d**2, axis=0) / 2.0) / SIGMA > 1.5)  # the mean's scale
    out = _run(detector, moved.mask(np.arange(n) >= n_cal))
    assert not out.alarm.any()


def test_a_quantised_output_needs_longer_runs_to_be_stuck():
    block = _gyro_log(1000, seed=106)
    lsb = 2 * SIGMA
    quantised = ImuBlock(t_ns=block.t_ns, gyro=np.round(block.gyro / lsb) * lsb)  # type: ignore[operator]
    fine = _fitted(block, false_alarms="1/h").models["gyro"]
    coarse = _fitted(quantised, false_alarms="1/h").models["gyro"]
    assert (coarse.repeat_p > 0.1).all() and (coarse.repeats > 3 * fine.repeats).all()


@pytest.mark.parametrize(
    ("raw", "fragment"),
    [
        ({"checks": "stuck,wobble"}, "unknown check 'wobble'"),
        ({"checks": ""}, "give at least one of"),
        ({"false_alarms": "-1/h"}, "must be >= 0"),
        ({"false_alarms": "3m"}, "frequency"),
        ({"types": "gyro,temp"}, "unknown sensor type"),
    ],
)
def test_bad_parameters(raw, fragment):
    with pytest.raises(DetectorConfigError, match=fragment):
        make_detector("health", raw)


def test_a_constant_calibration_is_refused():
    block = _gyro_log(1000, seed=107)
    gyro = block.gyro.copy()  # type: ignore[union-attr]
    gyro[:, 0, 2] = 0.0
    with pytest.raises(CalibrationError, match=r"imu0\.gyro\.z does not change"):
        _fitted(ImuBlock(t_ns=block.t_ns, gyro=gyro))


def test_one_imu_bag_with_a_stuck_gyro_is_detected_and_explained_under_1_per_hour(tmp_path):
    """The target: a one-IMU log, a stuck gyro axis, detect under a 1/h budget."""
    from tests.cli.conftest import invoke

    log, faulty, out = tmp_path / "one.mcap", tmp_path / "f.mcap", tmp_path / "d.mcap"
    assert (
        invoke(["simulate", "--imus", "1", "--duration", "40s", "--seed", "5", "-o", log]).code == 0
    )
    spec = "stuck:imu0.gyro.x,at=20s,duration=5s"
    assert invoke(["inject", log, "--fault", spec, "-o", faulty]).code == 0
    result = invoke(
        [
            "detect",
            faulty,
            "-d",
            "health",
            "--param",
            "health.false_alarms=1/h",
            "-o",
            out,
            "--json",
            "-",
        ]
    )
    assert result.code == 0, result.stderr
    summary = json.loads(result.stdout)
    health = summary["detectors"]["health"]
    assert health["gyro"]["episodes"] == {"stuck": 1}
    assert health["accel"]["episodes"] == {}


@pytest.mark.slow
def test_fault_free_episode_rate_stays_within_the_budget():
    """Fresh seeds (never used to tune): 10 h of one IMU's gyro at 100 Hz, budget 1/h, and
    2 h at a budget of 1/min. Every alarm run is counted as an episode (the pipeline merges
    runs, so this over-counts). Poisson tolerances: at the full budget the 99.9 % quantile
    of the count (Poisson(10): 21; Poisson(120): 155)."""
    for hours, budget, per_hour, limit in ((10, "1/h", 1.0, 21), (2, "1/min", 60.0, 155)):
        seed = 9000 + hours
        cal = _gyro_log(2000, seed=seed)
        detector = make_detector("health", {"types": "gyro", "false_alarms": budget})
        detector.fit(cal, ArrayConfig.co_aligned(1, RATE, sensors=("gyro",)))
        count = 0
        chunk = 360_000  # an hour at a time: memory flat in the log length
        carry = False
        for part in range(int(hours * 3600 * RATE) // chunk):
            block = _gyro_log(chunk, seed=seed * 100 + part, t0_ns=part * 3_600_000_000_000)
            alarm = detector.process(block)["gyro"].alarm
            starts = np.flatnonzero(alarm & ~np.concatenate([[carry], alarm[:-1]]))
            count += starts.size
            carry = bool(alarm[-1])
        assert count <= limit, (budget, count, hours * per_hour)
