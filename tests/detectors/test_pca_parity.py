"""pca-parity: moving windows, variance inflation, isolation, conical6 and bias cases."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose

from imufdi_cli.detectors import make_detector
from imufdi_cli.detectors.base import NO_ISOLATION, NOT_ISOLABLE, DetectionBlock, parse_params
from imufdi_cli.detectors.glt import GltDetector
from imufdi_cli.detectors.pca_parity import (
    PcaParityDetector,
    _lag_one_autocorrelation,
    cross_fit_split,
    cross_fitted_components,
    cross_validated_components,
    fold_labels,
    mean_variance_inflation,
    plug_in_quantile,
    principal_components,
)
from imufdi_cli.errors import ArrayTooSmallError, CalibrationError, DetectorConfigError
from imufdi_cli.faults import FaultInjector, parse_fault_spec
from imufdi_cli.log import ImuBlock, iter_blocks
from imufdi_cli.maths.parity import parity_matrix
from imufdi_cli.simulate import preset, simulate_block
from tests.detectors.budget_support import (
    fault_free_episodes,
    faulted_run,
    first_alarm_after,
    poisson_upper,
)

DEG = np.pi / 180.0


def make(params: dict | None = None) -> PcaParityDetector:
    return PcaParityDetector.from_params(params)  # old parameter names accepted, as on the CLI


def run(detector, array, block, calibrate=(0.0, 2.0), block_size=173):
    t = block.t_s()
    detector.fit(block.mask((t >= calibrate[0]) & (t < calibrate[1])), array)
    outs = [detector.process(b) for b in iter_blocks(block, block_size)]
    return {s: DetectionBlock.concatenate([o[s] for o in outs]) for s in outs[0]}


def conical6(seed: int, fault: bool = True):
    array, block = simulate_block(preset("conical6", seed=seed))
    if fault:
        faults = [parse_fault_spec("step:imu5.gyro.z,at=6s,amp=0.5deg/s", array)]
        block = FaultInjector(faults, array, seed=seed, t0_ns=int(block.t_ns[0])).apply_block(block)
    return array, block


def gyro_block(values: np.ndarray, rate_hz: float = 100.0) -> ImuBlock:
    """ImuBlock of co-aligned triads from (N, m, 3) gyro values."""
    t_ns = (np.arange(values.shape[0]) * 1e9 / rate_hz).astype(np.int64)
    return ImuBlock(t_ns=t_ns, gyro=values)


# --- helpers -------------------------------------------------------------------------


def test_variance_inflation_matches_the_ar1_sum():
    rho = np.array([0.0, 0.5, -0.3, 0.9])
    lengths = np.array([1, 7, 40])
    brute = np.array(
        [[1 + 2 * sum((1 - lag / n) * r**lag for lag in range(1, n)) for r in rho] for n in lengths]
    )
    assert_allclose(mean_variance_inflation(rho, lengths), brute, rtol=1e-12)
    # white noise: Var(mean of L) = sigma^2 / L exactly
    assert_allclose(mean_variance_inflation(np.zeros(1), np.arange(1, 5))[:, 0], 1.0)


# --- analytic isolation ----------------------------------------------------------------


def test_noise_free_fault_is_isolated_at_zero_angle_with_exact_amplitude():
    """A step f on sensor j moves the parity vector by f v_j: angle 0, amplitude f."""
    array, _ = simulate_block(preset("conical6", seed=3, noise_scale=0.0))
    H = array.measurement_matrix("gyro")
    rng = np.random.default_rng(0)
    n = 2000
    measurements = rng.standard_normal((n, 3)) @ H.T * 0.3 + 1e-3 * rng.standard_normal((n, 6))
    measurements[1000:, 2] += 0.01  # fault on sensor 2
    triads = np.full((n, 6, 3), np.nan)
    triads[:, :, 2] = measurements
    block = gyro_block(triads)
    detector = make({"leak": "none", "window": "0.5s"})
    out = run(detector, array, block, calibrate=(0.0, 9.0))["gyro"]
    late = slice(1200, 2000)
    assert out.alarm[late].all()
    assert (out.isolated[late] == 2).all()
    assert_allclose(out.amplitude[late], 0.01, rtol=0.05)
    assert np.all(out.scores[late, 2] < 0.1)  # radians
    V = parity_matrix(H)
    assert_allclose(detector.models["gyro"].projection, V)


def test_four_sensors_detect_but_cannot_isolate():
    """n = 4: one parity dimension, every v_j is parallel -> NOT_ISOLABLE."""
    conical = simulate_block(preset("conical6", seed=0, n_imus=4))[0]
    rng = np.random.default_rng(1)
    n = 1500
    values = 1e-3 * rng.standard_normal((n, 4))
    values[800:, 1] += 0.02
    triads = np.full((n, 4, 3), np.nan)
    triads[:, :, 2] = values
    out = run(make(), conical, gyro_block(triads))["gyro"]
    assert out.alarm[850:].all()
    assert set(np.unique(out.isolated[out.alarm])) == {NOT_ISOLABLE}


# --- reference scenario --------------------------------------------------------------


def test_conical6_fault_detected_isolated_and_quiet_before_with_motion_training():
    """Hao & Wang §4 case: training window 0-5 s contains the motion (leak regression)."""
    array, block = conical6(seed=0)
    t = block.t_s()
    out = run(make({"alpha": 0.001}), array, block, calibrate=(0.0, 5.0))["gyro"]
    assert not out.alarm[t < 6.0].any()
    hits = np.flatnonzero(out.alarm & (t >= 6.0))
    assert t[hits[0]] - 6.0 <= 0.5
    assert out.alarm[t >= 6.5].mean() > 0.99
    assert (out.isolated[hits] == 5).mean() > 0.99
    assert_allclose(np.median(out.amplitude[hits]), 0.5 * DEG, rtol=0.05)
    assert (out.isolated[~out.alarm] == NO_ISOLATION).all()


def test_raw_space_alarms_when_the_motion_starts():
    array, block = conical6(seed=1)
    t = block.t_s()
    out = run(make({"space": "raw"}), array, block, calibrate=(0.0, 1.0))["gyro"]
    first = t[np.flatnonzero(out.alarm)[0]]
    assert 1.0 <= first < 1.1
    assert out.alarm[(t >= 1.5) & (t < 6.0)].mean() > 0.9
    assert set(np.unique(out.isolated[out.alarm])) == {NOT_ISOLABLE}


def test_leak_regression_is_what_keeps_the_parity_test_quiet_under_motion():
    array, block = conical6(seed=2, fault=False)
    t = block.t_s()
    without = run(make({"leak": "none"}), array, block, calibrate=(0.0, 5.0))["gyro"]
    with_leak = run(make(), array, block, calibrate=(0.0, 5.0))["gyro"]
    after = t >= 5.0
    assert without.alarm[after].mean() > 0.05
    assert with_leak.alarm[after].mean() < 0.03


@pytest.mark.slow
def test_chip_biases_false_alarm_rate_is_nominal_while_plain_glt_alarms():
    rates = []
    for seed in range(3):
        array, block = simulate_block(
            preset(
                "paper-table4",
                seed=seed,
                outliers=False,
                duration=20.0,
                chip_biases={"gyro": "0.5deg/s"},
            )
        )
        out = run(make({"types": "gyro"}), array, block)["gyro"]
        rates.append(out.alarm.mean())
        glt = GltDetector(**parse_params(GltDetector.PARAMS, {"bias": False}, "glt"))
        plain = run(glt, array, block)["gyro"]
        assert plain.alarm.mean() > 0.5
    assert np.mean(rates) < 0.02  # nominal alpha = 0.01 (measured 0.002-0.007 per seed)


def test_streaming_gives_the_same_rows_for_any_block_size():
    array, block = conical6(seed=4)
    one = run(make(), array, block, block_size=len(block))["gyro"]
    many = run(make(), array, block, block_size=37)["gyro"]
    assert_allclose(one.statistic, many.statistic, rtol=1e-9)
    assert (one.alarm == many.alarm).all()
    assert (one.isolated == many.isolated).all()
    detector = make()
    detector.fit(block.slice(0, 200), array)
    assert [len(b) for b in detector.flush().values()] == [0]


# --- errors and metadata -------------------------------------------------------------


@pytest.mark.parametrize(
    ("raw", "match"),
    [
        ({"space": "pca"}, "valid: parity, raw"),
        ({"components": "0"}, ">= 1"),
        ({"window": "5m/s"}, "time"),
        ({"types": "gyro,baro"}, "valid: gyro, accel, mag"),
        ({"nope": "1"}, "valid: alpha"),
    ],
)
def test_bad_params_raise_detector_config_error(raw, match):
    with pytest.raises(DetectorConfigError, match=match):
        make(raw)


def test_short_or_missing_calibration_raises():
    array, block = conical6(seed=0, fault=False)
    with pytest.raises(CalibrationError, match="at least"):
        make().fit(block.slice(0, 15), array)
    with pytest.raises(ArrayTooSmallError, match="nothing to test"):
        make({"types": "accel"}).fit(block.slice(0, 200), array)
    with pytest.raises(CalibrationError, match="before fit"):
        make().process(block)


def test_metadata_is_json_ready():
    import json

    array, block = conical6(seed=0, fault=False)
    detector = make()
    detector.fit(block.slice(0, 500), array)
    meta = json.loads(json.dumps(detector.metadata()))
    assert meta["types"]["gyro"]["dimension"] == 3
    assert meta["types"]["gyro"]["components"] == 2
    assert meta["params"]["window_samples"] == 20
    assert meta["variances"].startswith("mixed")


# --- level out of sample, calibration coverage ------------------------------------


def far_bound(n_samples: int, level: float, window: int, z: float = 3.1) -> float:
    """Upper 99.9 % bound on the alarm count at per-sample rate ``level``.

    A moving-mean test's alarms come in clumps no longer than the window, so the variance
    of the count is at most ``window`` times the binomial one.
    """
    mean = n_samples * level
    return mean + z * np.sqrt(window * mean * (1.0 - level))


def test_prediction_leverage_is_the_regression_prediction_variance():
    """h = [1, x]^T (Z^T Z)^-1 [1, x] for the design Z = [1, X] of the training motion."""
    rng = np.random.default_rng(3)
    n = 6
    array, _ = conical6(seed=0, fault=False)
    H = array.measurement_matrix("gyro")
    rates = rng.standard_normal((400, 3)) * 0.3  # well excited in all three axes
    noise = rng.standard_normal((400, n)) * 1e-3
    detector = make({"window": "0.01s"})  # one-sample moving mean
    detector.window_samples = 1
    training = rates @ H.T + noise
    detector.models = {"gyro": detector._fit_type(training, H, "gyro")}
    model = detector.models["gyro"]
    estimates = training @ np.linalg.pinv(H).T
    design = np.hstack([np.ones((400, 1)), estimates])
    new = rng.standard_normal((5, 3)) * 2.0
    expected = np.einsum(
        "ij,jk,ik->i",
        np.hstack([np.ones((5, 1)), new]),
        np.linalg.inv(design.T @ design),
        np.hstack([np.ones((5, 1)), new]),
    )
    extra, _ = model.leverage(new)
    assert_allclose(1.0 / 400 + extra, expected, rtol=1e-8)


def test_conical6_level_holds_after_the_documented_calibration():
    """Documented setup (alpha 0.001, 0-5 s): FAR after calibration was 8.6 alpha."""
    alarms = total = 0
    detector = make({"alpha": 0.001})
    for seed in (3, 4):
        array, block = conical6(seed, fault=False)
        out = run(detector, array, block, calibrate=(0.0, 5.0))["gyro"]
        after = block.t_s() >= 5.0
        alarms += int(out.alarm[after].sum())
        total += int(after.sum())
        assert detector.calibration_warnings() == []
    assert alarms <= far_bound(total, 1.5 * detector.alpha, detector.window_samples)


def test_calibration_without_the_motion_is_reported_and_fatal_under_strict(tmp_path):
    """Default 0-2 s window on conical6 (1 s of ramping motion): warned, exit 3 under --strict."""
    detector = make()
    array, block = conical6(seed=5, fault=False)
    run(detector, array, block, calibrate=(0.0, 2.0))
    (message,) = detector.calibration_warnings()
    assert "lacks the motion" in message and "% of the samples" in message
    assert detector.metadata()["types"]["gyro"]["samples_beyond_calibrated_motion"] > 0

    from tests.cli.conftest import assert_one_line_error, invoke

    log = tmp_path / "c6.mcap"
    assert invoke(["simulate", "--preset", "conical6", "--seed", "5", "-o", log]).code == 0
    # the warning and the exit codes only: no episode explanations (--no-explain)
    ok = invoke(["detect", log, "-d", "pca-parity", "--no-explain", "-o", tmp_path / "a.mcap"])
    assert ok.code == 0 and "lacks the motion" in ok.stderr + ok.out
    strict = invoke(["detect", log, "-d", "pca-parity", "-o", tmp_path / "b.mcap", "--strict"])
    assert_one_line_error(strict, 3, "lacks the motion")
    assert not (tmp_path / "b.mcap").exists()
    wide = ["detect", log, "-d", "pca-parity", "--no-explain", "-o", tmp_path / "c.mcap"]
    wide += ["--calibrate", "0s:5s"]
    assert invoke([*wide, "--strict"]).code == 0


def test_accelerometers_with_lever_arms_are_tested_on_the_rigid_body_design(scipy_stats):
    """wearable12: IMUs 3 cm apart; the parity space of [H | lever-arm columns]
    (maths/rigid.py) cancels the rotation, so the accelerometers are tested."""
    array, block = simulate_block(preset("wearable12", seed=0, duration=8.0))
    detector = make()
    out = run(detector, array, block)
    assert set(out) == {"gyro", "accel"}
    assert "accel" not in detector.metadata()["untested"]
    t = block.t_s()
    after = int(np.count_nonzero(t >= 2.0))  # out of sample: after the calibration window
    alarms = int(np.count_nonzero(out["accel"].alarm[-after:]))
    # at most the binomial 99.9 % quantile at 3 alpha (a moving-window test: its alarms
    # come in runs, hence the margin); without the lever-arm model this was ~25 alpha
    assert alarms <= scipy_stats.binom.ppf(0.999, after, 3 * detector.alpha)


# --- calibration of the variances (cross-fitting, F thresholds, rho floor) ------


def test_cross_fitted_variance_is_unbiased_where_the_smallest_eigenvalue_is_not():
    """Isotropic white noise (q = 3, N = 500, sigma = 1): the smallest sample eigenvalue is
    biased low (its direction minimises the variance of the same data); the cross-fitted
    variance of the last direction is unbiased (directions from half A, variance from B).

    Tolerance: each cross-fitted variance is chi2(N_B)/N_B with sd sqrt(2/N_B); the mean of
    R replications has sd sqrt(2/(N_B R)), and 4 sd bound it (two-sided 6e-5).
    """
    rng = np.random.default_rng(16)
    n_rows, q, reps, block = 500, 3, 400, 20
    smallest, crossed = [], []
    for _ in range(reps):
        rows = rng.standard_normal((n_rows, q))
        centred = rows - rows.mean(axis=0)
        smallest.append(np.linalg.eigvalsh(centred.T @ centred / (n_rows - 1))[0])
        variances, directions = cross_fitted_components(centred, block)
        assert_allclose(directions.T @ directions, np.eye(q), atol=1e-12)
        crossed.append(variances[-1])
    n_b = n_rows - cross_fit_split(n_rows, block)
    sd = np.sqrt(2.0 / (n_b * reps))
    assert abs(np.mean(crossed) - 1.0) < 4 * sd
    assert np.mean(smallest) < 1.0 - 10 * sd  # measured about 0.9


def test_cross_fit_halves_alternate_blocks_and_span_the_window():
    assert cross_fit_split(200, 20) == 100
    assert cross_fit_split(210, 20) == 110  # the last, partial block belongs to half A
    assert cross_fit_split(12, 20) == 6  # block capped at a quarter of the rows


def test_windows_shorter_than_the_parity_dimension_still_give_variances():
    """paper-table4 (45 parity dimensions per type) on 0.5 s: 50 rows, each fold's rest 45,
    no more than the dimensions. The out-of-fold directions are then partly arbitrary, but
    the held-out variance along each is still a positive estimate, counted on N/2 = 25
    degrees of freedom (the kept components' eigenvalues on N - 1 = 49), which the F
    thresholds take into account."""
    array, block = simulate_block(preset("paper-table4", seed=1, duration=2.0, outliers=False))
    detector = make()
    out = run(detector, array, block, calibrate=(0.0, 0.5))
    assert set(out) == {"gyro", "accel"}
    meta = detector.metadata()["types"]["gyro"]
    assert meta["dimension"] == 45
    dof = meta["variance_dof"]  # rows (1 - r^2) / (1 + r^2): N - 1 kept, N / 2 discarded
    assert 35 < min(dof[:2]) <= max(dof[:2]) <= 49
    assert 15 < min(dof[2:]) <= max(dof[2:]) <= 25


def test_plug_in_quantile_is_student_squared_for_one_component(scipy_stats):
    """X = z^2 / s^2 with s^2 on nu degrees of freedom is t(nu)^2 = F(1, nu)."""
    for nu in (5.0, 50.0, 400.0):
        expected = scipy_stats.t.ppf(1.0 - 0.0005 / 2.0, nu) ** 2
        assert_allclose(plug_in_quantile(0.0005, np.array([1.0]), nu), [expected], rtol=1e-9)
    assert_allclose(
        plug_in_quantile(0.01, np.array([2.0, 3.0]), np.inf), scipy_stats.chi2.ppf(0.99, [2.0, 3.0])
    )


def test_chance_negative_autocorrelation_is_floored_at_zero():
    """An alternating sequence has lag-one autocorrelation -1; the moving-mean variance
    must not shrink on such an estimate (the floor is 0), a positive one is kept."""
    alternating = np.tile([1.0, -1.0], 50)[:, None]
    assert _lag_one_autocorrelation(alternating)[0] == 0.0
    rng = np.random.default_rng(1)
    ar = np.zeros(5000)
    for i in range(1, ar.size):
        ar[i] = 0.5 * ar[i - 1] + rng.standard_normal()
    assert abs(_lag_one_autocorrelation((ar - ar.mean())[:, None])[0] - 0.5) < 0.05


def test_every_leak_is_kept_once_one_is_significant_and_none_without_motion_leak():
    """conical6, default 0-2 s window (1 s of ramping motion): scale and misalignment errors
    leak into every parity component; the F test sees some of them on 1 s of motion, and
    then every component's fitted leak is kept (dropping one left its whole leak in the
    test: 8.2 alpha). wearable12 (co-aligned, no scale errors): no leak is significant, and
    none is fitted, so the motion range does not widen its thresholds."""
    detector = make()
    array, block = simulate_block(preset("conical6", seed=3, duration=4.0))
    run(detector, array, block, calibrate=(0.0, 2.0))
    leak = np.asarray(detector.metadata()["types"]["gyro"]["leak_matrix"])
    assert np.all(np.any(leak != 0.0, axis=1))
    detector = make()
    array, block = simulate_block(preset("wearable12", seed=3, duration=4.0))
    run(detector, array, block, calibrate=(0.0, 2.0))
    for sensor_type in ("gyro", "accel"):
        assert not np.any(detector.metadata()["types"][sensor_type]["leak_matrix"])


@pytest.mark.slow
def test_conical6_level_holds_on_long_logs_after_the_documented_calibration():
    """Mean target (<= 1.5 alpha) on 200 s logs (documented setup, alpha = 0.001, 0-5 s),
    where a 20 s log's single episode already weighs 6 alpha.

    The bound is ``far_bound``: the 99.9 % quantile of the alarm count at 1.5 alpha with
    the count's variance inflated by the window (alarms come in clumps). The worst-seed
    target is not asserted: the calibration's own errors (leak, variances) are fixed for a
    whole log, so the per-log level varies around alpha whatever the log's length
    (docs/algorithms/pca-parity.md, "Worst seed").
    """
    detector = make({"alpha": 0.001})
    alarms = total = 0
    for seed in (3, 4):
        array, block = simulate_block(preset("conical6", seed=seed, duration=200.0))
        out = run(detector, array, block, calibrate=(0.0, 5.0), block_size=4096)["gyro"]
        after = block.t_s() >= 5.0
        alarms += int(out.alarm[after].sum())
        total += int(after.sum())
    assert alarms <= far_bound(total, 1.5 * detector.alpha, detector.window_samples)


# --- out-of-fold variances: the level of the halves at full length (power) ------------


def test_fold_labels_interleave_blocks_and_fill_every_fold():
    labels = fold_labels(200, 20, 10)
    assert_allclose(labels[::20], np.arange(10))  # one 20-row block per fold, in turn
    assert np.all(np.bincount(labels) == 20)
    short = fold_labels(30, 20, 10)  # blocks shortened so that every fold gets rows
    assert set(short.tolist()) == set(range(10))


@pytest.mark.slow  # 400 replications, statistical (4 sd); 0.4-0.65 s of CPU
def test_out_of_fold_variance_is_unbiased_where_the_smallest_eigenvalue_is_not():
    """Isotropic white noise (q = 3, N = 500, sigma = 1): the out-of-fold variance of the
    last whole-window direction is unbiased, where its eigenvalue is about 0.9.

    Tolerance: the detector counts each out-of-fold variance on N/2 degrees of freedom
    (measured: sd 0.089 at N = 500, sqrt(2/250) = 0.089); the mean of R replications has
    sd sqrt(2/(N/2 R)), and 4 sd bound it (two-sided 6e-5).
    """
    rng = np.random.default_rng(17)
    n_rows, q, reps = 500, 3, 400
    values = []
    for _ in range(reps):
        rows = rng.standard_normal((n_rows, q))
        centred = rows - rows.mean(axis=0)
        variances, directions = cross_validated_components(centred, 20, 10)
        assert_allclose(directions.T @ directions, np.eye(q), atol=1e-12)
        whole = np.linalg.eigh(centred.T @ centred)[1][:, ::-1]
        assert_allclose(np.abs(directions.T @ whole), np.eye(q), atol=1e-9)  # whole window
        values.append(variances[-1])
    sd = np.sqrt(2.0 / (n_rows / 2 * reps))
    assert abs(np.mean(values) - 1.0) < 4 * sd


def test_mixed_variances_keep_the_eigenvalues_of_the_kept_components():
    """Isotropic noise in 45 dimensions on 200 rows (paper-table4's gyro parity space):
    the two kept components keep their sample eigenvalues, which lie near the upper edge
    of the Marchenko-Pastur bulk, (1 + sqrt(45/200))^2 = 2.2, far above the true 1: the T
    test is conservative there and cannot take the false-alarm budget of the Q test, which
    carries a fault of a random direction (the power lost by the halves at matched FAR).
    The discarded ones get out-of-fold variances, unbiased on average: their mean over
    the 43 directions has sd at most sqrt(2/(N/2 * 43)) per replication (the detector's
    N/2 dof; measured 0.016 against 0.022), and 4 sd of the mean of R replications bound
    it. The sample eigenvalues average 0.95 there (biased low: the Q test was liberal),
    more than 8 sd below 1."""
    rng = np.random.default_rng(18)
    n_rows, q, k, reps = 200, 45, 2, 40
    kept, tail, sample_tail = [], [], []
    for _ in range(reps):
        rows = rng.standard_normal((n_rows, q))
        centred = rows - rows.mean(axis=0)
        variances, _directions, dof_rows = principal_components(centred, k, 20)
        eigenvalues = np.linalg.eigvalsh(centred.T @ centred / (n_rows - 1))[::-1]
        assert_allclose(variances[:k], eigenvalues[:k], rtol=1e-9)
        assert_allclose(dof_rows, [n_rows - 1] * k + [n_rows / 2] * (q - k))
        kept.append(variances[:k])
        tail.append(variances[k:].mean())
        sample_tail.append(eigenvalues[k:].mean())
    assert np.min(kept) > 1.5
    sd = np.sqrt(2.0 / (n_rows / 2 * (q - k) * reps))
    assert abs(np.mean(tail) - 1.0) < 4 * sd
    assert np.mean(sample_tail) < 1.0 - 8 * sd


def matched_far_mar(statistic, t, onset, calibration_end=2.0, far=0.01):
    """MAR with the threshold at the (1 - far) quantile of the out-of-sample fault-free
    statistic (the campaign's ``mar_at_far``, per run)."""
    free = (t >= calibration_end) & (t < onset)
    threshold = np.quantile(statistic[free], 1.0 - far)
    return float(np.mean(statistic[t >= onset] <= threshold))


@pytest.mark.slow
def test_small_step_power_at_matched_far_is_not_lost_to_the_kept_components():
    """paper-table4, 0.3 deg/s step on imu0.gyro.x, tuning seeds 0-9, MAR at matched FAR 1 %.

    The halves (``cross_fitted_components``) left the kept components' variances 2-3 sd
    low on some seeds; the T test then alarmed on the fault-free part, the matched
    threshold rose and the Q test, which carries the fault, lost it (compare seeds
    1000/1017: 53 % and 66 %; here seed 8: 75 %, mean over seeds 0-9: 12.8 %). Bound: the
    figure of the detector before its calibration changes (sample eigenvalues), mean 2.8 %
    over 20 seeds, plus 3 standard errors of a mean of 10 seeds with a seed-to-seed sd of 5 %
    (heavier than the 1.9 % measured, to allow a seed like tuning seed 13 at 17 %): 7.5 %.
    """
    detector = make({"types": "gyro"})
    mars = []
    for seed in range(10):
        array, block = simulate_block(preset("paper-table4", seed=seed, duration=20.0))
        faults = [parse_fault_spec("step:imu0.gyro.x,at=12s,amp=0.3deg/s", array)]
        block = FaultInjector(faults, array, seed=seed, t0_ns=int(block.t_ns[0])).apply_block(block)
        out = run(detector, array, block, block_size=4096)["gyro"]
        mars.append(matched_far_mar(out.statistic, block.t_s(), 12.0))
    assert np.mean(mars) <= 0.028 + 3 * 0.05 / np.sqrt(10)


def test_worst_motion_leak_error_of_one_calibration_is_chi2_with_mean_e():
    """Scheffe: for a least-squares fit on a design X (N, e), the error d of the fitted
    coefficients satisfies sup_x (x.d)^2 / (sigma^2 x^T G x) = d^T G^-1 d / sigma^2 ~
    chi2(e), G = (X^T X)^-1. Its mean, e, is the allowance the detector puts on the leak
    error term (SCHEFFE_LEAK). Tolerance: 4 sd of the mean of R chi2(e) draws,
    4 sqrt(2 e / R)."""
    rng = np.random.default_rng(19)
    n_rows, e, reps = 200, 3, 2000
    design = rng.standard_normal((n_rows, e)) * np.array([1.0, 5.0, 20.0])
    gram = design.T @ design
    ratios = []
    for _ in range(reps):
        noise = rng.standard_normal(n_rows)
        error = np.linalg.solve(gram, design.T @ noise)  # fitted minus true coefficients
        ratios.append(error @ gram @ error)
    assert abs(np.mean(ratios) - e) < 4 * np.sqrt(2 * e / reps)


def test_leak_error_allowance_is_the_number_of_excited_directions(monkeypatch):
    """conical6 on 0-2 s: three excited directions, a leak fitted: allowance 3. wearable12
    swings too, but no leak is significant, none is fitted, and the statistic is the same
    with and without the allowance."""
    detector = make()
    array, block = simulate_block(preset("conical6", seed=3, duration=4.0))
    run(detector, array, block, calibrate=(0.0, 2.0))
    model = detector.models["gyro"]
    assert model.leak_fitted and model.motion.basis.shape[1] == 3
    assert model.leak_tolerance == 3.0
    from imufdi_cli.detectors import pca_parity

    array, block = simulate_block(preset("wearable12", seed=3, duration=4.0))
    with_allowance = run(make(), array, block, calibrate=(0.0, 2.0))
    monkeypatch.setattr(pca_parity.choices, "SCHEFFE_LEAK", False)
    without = run(make(), array, block, calibrate=(0.0, 2.0))
    for sensor_type, out in with_allowance.items():
        assert_allclose(out.statistic, without[sensor_type].statistic, rtol=0, atol=0)


# --- under a false-alarm budget ------------------------------------------------------------

BUDGET = {"false_alarms": "1/h"}


@pytest.mark.parametrize(
    ("amplitude", "within_s"),
    [(0.9, 0.06), (0.3, 0.3)],  # Lorden's references at 1/h: about 0.01 s and 0.09 s
)
def test_budget_detects_isolates_and_sizes_a_step_fast(amplitude: float, within_s: float) -> None:
    spec = f"step:imu3.gyro.y,at=30s,amp={amplitude}deg/s"
    array, out, _ = faulted_run("pca-parity", BUDGET, "paper-table4", (spec,), 35001, 40.0)
    gyro = out["gyro"]
    onset = 3000 - 200  # rows start after the 2 s calibration window
    assert not gyro.alarm[:onset].any()
    first = first_alarm_after(gyro, onset)
    assert first is not None and first <= onset + within_s * 100
    alarmed = gyro.isolated[gyro.alarm]
    assert np.mean(alarmed == array.sensor_ids("gyro").index("imu3.gyro.y")) > 0.99
    assert np.median(gyro.amplitude[gyro.alarm]) == pytest.approx(amplitude * DEG, rel=0.1)
    assert not out["accel"].alarm.any()


def test_budget_hold_is_a_time_or_latch_and_only_under_a_budget() -> None:
    assert make({**BUDGET, "hold": "latch"}).hold_s == math.inf
    assert make({**BUDGET, "hold": "0s"}).hold_s == 0.0
    with pytest.raises(DetectorConfigError, match="under a false-alarm budget"):
        make({"hold": "20s"})
    with pytest.raises(DetectorConfigError, match=r"hold: '-1s' is not a time"):
        make({**BUDGET, "hold": "-1s"})


def test_a_latched_budget_keeps_a_lasting_step_in_alarm() -> None:
    # the 0.3 deg/s step for 80 s: latched, one episode to the end of the log
    spec = "step:imu3.gyro.y,at=20s,amp=0.3deg/s"
    params = {**BUDGET, "hold": "latch"}
    _, out, det = faulted_run("pca-parity", params, "paper-table4", (spec,), 35001, 100.0)
    gyro = out["gyro"]
    first = first_alarm_after(gyro, 2000 - 200)
    assert first is not None and gyro.alarm[first:].all()
    assert det.metadata()["types"]["gyro"]["budget"]["hold_s"] is None


def _common_mode_log(seed: int, onset_s: float | None):
    """paper-table4 (no spikes) with a common mode of 2 sigma on the x gyros of IMUs 0-7
    and, anti-correlated, 1.4 sigma on the y gyros of IMUs 8-15 (a shared disturbance), and
    a 0.3 deg/s step on imu3.gyro.x at ``onset_s``."""
    array, block = simulate_block(preset("paper-table4", seed=seed, duration=40.0, outliers=False))
    common = np.random.default_rng(seed + 7).standard_normal(len(block)) * 2.0 * 0.15 * DEG
    gyro = block.gyro.copy()
    gyro[:, :8, 0] += common[:, None]
    gyro[:, 8:, 1] -= 0.7 * common[:, None]
    block = ImuBlock(t_ns=block.t_ns, gyro=gyro, accel=block.accel)
    if onset_s is not None:
        fault = parse_fault_spec(f"step:imu3.gyro.x,at={onset_s}s,amp=0.3deg/s", array)
        block = FaultInjector([fault], array, seed=seed, t0_ns=int(block.t_ns[0])).apply_block(
            block
        )
    return array, block


def test_budget_whitens_a_common_mode_that_glt_takes_for_independent_noise() -> None:
    # glt's evidence assumes independent sensors: the common mode inflates the sigma of
    # every sensor it touches; pca-parity learns it as a correlated component of the
    # parity covariance (one spike) and whitens it: the step is found about twice as fast
    delays = {"glt": [], "pca-parity": []}
    for seed in (35011, 35012, 35013):
        array, block = _common_mode_log(seed, 30.0)
        for name in delays:
            detector = make_detector(name, BUDGET)
            detector.fit(block.slice(0, 200), array)
            gyro = detector.process(block.slice(200, len(block)))["gyro"]
            onset = 3000 - 200
            assert not gyro.alarm[:onset].any(), name
            first = first_alarm_after(gyro, onset)
            assert first is not None
            delays[name].append(first - onset)
            assert np.mean(gyro.isolated[gyro.alarm] == 9) > 0.99  # imu3.gyro.x
        budget = detector.metadata()["types"]["gyro"]["budget"]
        assert len(budget["correlated_components"]) == 1
    assert np.mean(delays["pca-parity"]) < 0.7 * np.mean(delays["glt"])


def test_budget_learns_the_motion_leak_on_conical6_and_finds_a_fault_in_motion() -> None:
    # calibrated on 0-2 s (1 s of it in motion): scale and misalignment errors leak the
    # motion into the parity vector, a bias the calibration's fit leaves by up to 0.5 sd;
    # the leak is learnt online by the bank's motion model, which widens the test meanwhile
    spec = "step:imu5.gyro.z,at=300s,amp=0.15deg/s"
    _, out, detector = faulted_run("pca-parity", BUDGET, "conical6", (spec,), 35021, 310.0)
    gyro = out["gyro"]
    onset = 30000 - 200
    assert not gyro.alarm[:onset].any()
    first = first_alarm_after(gyro, onset)
    assert first is not None and first <= onset + 30
    assert np.mean(gyro.isolated[gyro.alarm] == 5) > 0.99
    budget = detector.metadata()["types"]["gyro"]["budget"]
    # the scale and misalignment leak learnt: its slopes known to a tenth of their size
    slopes, sd = np.abs(budget["motion_slopes"]), np.array(budget["motion_slope_sd"])
    assert sd.max() < 0.1 * slopes.max()


def test_budget_refuses_the_per_sample_options() -> None:
    for raw in (
        {"window": "0.5s"},
        {"components": "3"},
        {"residual_test": "false"},
        {"space": "raw"},
    ):
        with pytest.raises(DetectorConfigError, match="per-sample test"):
            make({**BUDGET, **raw})


def test_budget_metadata_is_json_ready_and_the_per_sample_metadata_is_unchanged() -> None:
    import json

    array, block = simulate_block(preset("wearable12", seed=35031, duration=4.0))
    for params in ({}, BUDGET):
        detector = make(params)
        detector.fit(block.slice(0, 200), array)
        detector.process(block.slice(200, len(block)))
        meta = detector.metadata()
        json.dumps(meta)
        for sensor_type in ("gyro", "accel"):
            assert ("budget" in meta["types"][sensor_type]) == bool(params)
        assert ("false_alarms_per_hour" in meta["params"]) == bool(params)
    budget = meta["types"]["accel"]["budget"]
    assert budget["false_alarms_per_hour"] == pytest.approx(1.0)
    assert budget["hypotheses"] == 2 * 36 and budget["correlated_components"] == []
    assert meta["params"]["track_bias"] == 60.0


@pytest.mark.slow
def test_budget_holds_on_hours_of_fault_free_logs_of_every_preset() -> None:
    # fresh development seeds; 2 h per preset: gyros 6 h, accelerometers 4 h; the target
    # (issue: at most 1 false episode an hour per channel pooled over the presets, its 95 %
    # upper bound <= 2/h); the design expects about 0.5 of the budget
    pooled: dict[str, list[float]] = {}
    for preset_name in ("paper-table4", "conical6", "wearable12"):
        counts, hours = fault_free_episodes("pca-parity", BUDGET, preset_name, 2.0, 35041)
        for sensor_type, episodes in counts.items():
            pooled.setdefault(sensor_type, [0, 0.0])
            pooled[sensor_type][0] += episodes
            pooled[sensor_type][1] += hours
    for sensor_type, (episodes, hours) in pooled.items():
        assert poisson_upper(int(episodes), hours) <= 2.0, (sensor_type, episodes, hours)
