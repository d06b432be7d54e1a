"""noise-glr: leave-one-out residuals, lever-arm model, GLR threshold, wearable12 case."""

from __future__ import annotations

import functools
import json

import numpy as np
import pytest
from numpy.testing import assert_allclose

from imufdi_cli.array import ArrayConfig
from imufdi_cli.detectors.base import NO_ISOLATION, DetectionBlock, parse_params
from imufdi_cli.detectors.noise_glr import (
    DEFAULT_LEVEL_CONFIDENCE,
    NoiseGlrDetector,
    calibration_factor,
    centripetal,
    clipped_square_moments,
    equivalent_dof,
    leave_one_out_operator,
    residual_spread,
    robust_scale,
    scale_estimator_dof,
    skew,
)
from imufdi_cli.errors import CalibrationError, DetectorConfigError
from imufdi_cli.faults import FaultInjector, parse_fault_spec
from imufdi_cli.log import ImuBlock, iter_blocks
from imufdi_cli.simulate import preset, simulate_block


def make(params: dict | None = None) -> NoiseGlrDetector:
    return NoiseGlrDetector(**parse_params(NoiseGlrDetector.PARAMS, params or {}, "noise-glr"))


def run(detector, array, block, calibrate=(0.0, 2.0), block_size=211):
    t = block.t_s()
    detector.fit(block.mask((t >= calibrate[0]) & (t < calibrate[1])), array)
    outs = [detector.process(b) for b in iter_blocks(block, block_size)]
    return {s: DetectionBlock.concatenate([o[s] for o in outs]) for s in outs[0]}


def wearable12(seed: int, factor: float | None = 3.0, **overrides):
    array, block = simulate_block(preset("wearable12", seed=seed, **overrides))
    if factor is not None:
        spec = f"noise:imu0.accel.x,at=12s,until=18s,factor={factor}"
        faults = [parse_fault_spec(spec, array)]
        block = FaultInjector(faults, array, seed=seed, t0_ns=int(block.t_ns[0])).apply_block(block)
    return array, block


def test_leave_one_out_operator_equals_explicit_refits():
    rng = np.random.default_rng(0)
    model = rng.standard_normal((9, 4))
    measurements = rng.standard_normal((5, 9))
    operator, testable = leave_one_out_operator(model)
    fast = measurements @ operator.T
    for j in range(9):
        keep = np.arange(9) != j
        x, *_ = np.linalg.lstsq(model[keep], measurements[:, keep].T, rcond=None)
        assert_allclose(fast[:, j], measurements[:, j] - model[j] @ x, atol=1e-12)
    assert testable.all()


def test_non_redundant_sensor_is_not_testable():
    model = np.vstack([np.eye(3), np.eye(3)[:2]])  # z measured once
    _, testable = leave_one_out_operator(model)
    assert testable.tolist() == [True, True, False, True, True]


def test_centripetal_and_skew_match_cross_products():
    rng = np.random.default_rng(1)
    rate, positions = rng.standard_normal((4, 3)), rng.standard_normal((3, 3))
    expected = np.cross(rate[:, None, :], np.cross(rate[:, None, :], positions[None]))
    assert_allclose(centripetal(rate, positions), expected, atol=1e-12)
    assert_allclose(skew(positions) @ rate[0], np.cross(positions, rate[0]), atol=1e-12)


def test_lever_arm_model_explains_noise_free_swinging_accelerometers_exactly():
    array, block = wearable12(0, factor=None, noise_scale=0.0)
    detector = make()
    t = block.t_s()
    calibration = block.mask(t < 2.0)
    # a zero residual variance is degenerate: fit must refuse it, with a clear message
    with pytest.raises(CalibrationError, match="variance"):
        detector.fit(calibration, array)
    model = detector.models.get("accel")
    assert model is None
    # compute the residuals directly with a probe calibrated on the noisy log
    noisy_array, noisy = wearable12(0, factor=None)
    detector.fit(noisy.mask(t < 2.0), noisy_array)
    residuals = detector._residuals("accel", detector.models["accel"], block)
    assert_allclose(residuals, 0.0, atol=1e-9)
    without = make({"lever_arm": False})
    without.fit(noisy.mask(t < 2.0), noisy_array)
    assert np.abs(without._residuals("accel", without.models["accel"], block)).max() > 0.05


def test_threshold_is_the_known_variance_quantile_raised_by_the_calibration_factor(scipy_stats):
    array, block = wearable12(0, factor=None)
    detector = make({"alpha": 0.01, "window": "0.3s"})
    detector.fit(block.slice(0, 200), array)
    model = detector.models["accel"]
    level = 1 - 0.99 ** (1 / 36)
    assert_allclose(model.sensor_level, level, rtol=1e-12)
    moments = clipped_square_moments(3.0)
    nu = equivalent_dof(np.array([30]), moments)[0]
    nu_cal = scale_estimator_dof(199, 3.0)
    known = scipy_stats.chi2.isf(level, nu) / nu
    factor = nu_cal / scipy_stats.chi2.ppf(1 - DEFAULT_LEVEL_CONFIDENCE, nu_cal)
    assert_allclose(model.critical_ratio[-1], known * factor, rtol=1e-12)
    assert_allclose(model.threshold[-1], nu / 2 * (known * factor - 1 - np.log(known * factor)))
    # level_confidence = 0: the predictive F threshold (level alpha on average only)
    predictive = make({"alpha": 0.01, "window": "0.3s", "level_confidence": 0})
    predictive.fit(block.slice(0, 200), array)
    critical = scipy_stats.f.ppf(1 - level, nu, nu_cal)
    assert_allclose(predictive.models["accel"].critical_ratio[-1], critical, rtol=1e-12)
    assert critical < known * factor
    # without clipping: nu_k = 2 k^2 / (3 k - 1), the differenced white-noise sum
    assert_allclose(equivalent_dof(np.array([30]), clipped_square_moments(1e3)), 1800 / 89)


def test_wearable12_noise_growth_detected_isolated_and_recovered():
    """Chen et al. §3: x3 noise on imu0.accel.x, 12-18 s (figures in the docs: 20 seeds)."""
    array, block = wearable12(seed=0)
    t = block.t_s()
    out = run(make({"alpha": 0.001}), array, block)["accel"]
    fault = (t >= 12.0) & (t < 18.0)
    hits = np.flatnonzero(out.alarm & fault)
    assert t[hits[0]] - 12.0 <= 0.4
    assert out.alarm[hits[0] : np.flatnonzero(fault)[-1] + 1].mean() >= 0.98
    cleared = np.flatnonzero(~out.alarm & (t >= 18.0))
    assert t[cleared[0]] - 18.0 <= 0.5
    assert out.alarm[~fault & (t < 12.0)].mean() <= 0.01
    assert (out.isolated[hits] == 0).mean() > 0.99
    assert_allclose(np.median(out.amplitude[hits]), 3.0, rtol=0.2)
    assert (out.isolated[~out.alarm] == NO_ISOLATION).all()


@pytest.mark.slow
def test_false_alarm_rate_is_at_most_alpha_without_fault():
    """Mean level over 6 wearable12 logs and both types, out of sample: at most alpha
    (the default level_confidence makes it lower), 99.9 % bound with clumped alarms."""
    detector = make()
    total, alarms = 0, 0
    for seed in range(6):
        array, block = wearable12(seed, factor=None)
        out = run(detector, array, block)
        after = block.t_s() >= 2.0
        for sensor_type in ("gyro", "accel"):
            total += int(after.sum())
            alarms += int(out[sensor_type].alarm[after].sum())
    assert alarms <= far_bound(total, detector.alpha, detector.window_samples)


def test_streaming_gives_the_same_rows_for_any_block_size():
    array, block = wearable12(seed=1)
    block = block.slice(0, 1500)
    one = run(make(), array, block, block_size=len(block))["accel"]
    many = run(make(), array, block, block_size=7)["accel"]
    assert_allclose(one.statistic, many.statistic, rtol=1e-9)
    assert (one.isolated == many.isolated).all()


@pytest.mark.parametrize(
    ("raw", "match"),
    [
        ({"window": "-1s"}, "must be >"),
        ({"alpha": "0.9"}, "<= 0.5"),
        ({"types": "baro"}, "valid: gyro, accel, mag"),
        ({"lever_arm": "maybe"}, "boolean"),
    ],
)
def test_bad_params_raise_detector_config_error(raw, match):
    with pytest.raises(DetectorConfigError, match=match):
        make(raw)


def test_short_calibration_raises_and_metadata_is_json_ready():
    import json

    array, block = wearable12(0, factor=None)
    with pytest.raises(CalibrationError, match="at least"):
        make().fit(block.slice(0, 30), array)
    detector = make()
    detector.fit(block.slice(0, 200), array)
    meta = json.loads(json.dumps(detector.metadata()))
    assert meta["types"]["accel"]["lever_arm"] is True
    assert meta["types"]["gyro"]["lever_arm"] is False


@pytest.mark.slow
def test_default_parameters_meet_the_wearable12_noise_growth_targets():
    """The targets of docs/algorithms/noise-glr.md, defaults, 3 seeds, as `imufdi detect`/`report` measure them."""
    from imufdi_cli.metrics import FaultWindow, compute_metrics

    rows = []
    for seed in (0, 1, 2):
        array, block = wearable12(seed)
        out = run(make(), array, block, block_size=4096)["accel"]
        t = block.t_s()
        j = array.sensor_ids("accel").index("imu0.accel.x")
        in_fault = (t >= 12.0) & (t < 18.0)
        faulty = np.zeros((len(t), out.scores.shape[1]), dtype=bool)
        faulty[in_fault, j] = True
        t0 = int(block.t_ns[0])
        window = FaultWindow("noise", (j,), t0 + 12 * 10**9, t0 + 18 * 10**9)
        m = compute_metrics(block.t_ns, out.alarm, out.isolated, faulty, [window])
        first = np.flatnonzero(out.alarm & in_fault)[0]
        rate = out.alarm[first : np.flatnonzero(in_fault)[-1] + 1].mean()
        rows.append((m.far, m.detection_delay_s, rate, m.recovery_delay_s))
        assert m.faults[0].isolated_correctly == pytest.approx(1.0)
    far, delay, rate, recovery = np.mean(np.array(rows, dtype=float), axis=0)
    assert far <= 0.01
    assert delay <= 0.4
    assert rate >= 0.98
    assert recovery <= 0.5


def test_end_of_fault_release_shortens_the_alarm_tail():
    array, block = wearable12(0)
    t = block.t_s()
    with_release = run(make(), array, block)["accel"]
    without = run(make({"release": 0.0}), array, block)["accel"]
    tail = t >= 18.0
    assert with_release.alarm[tail].sum() < without.alarm[tail].sum()
    # the release never adds alarms
    assert not np.any(with_release.alarm & ~without.alarm)


# --- variance, not mean; robust to outliers; level out of sample -------------------


def paper_table4(seed: int, specs: tuple[str, ...] = (), **overrides):
    array, block = simulate_block(preset("paper-table4", seed=seed, **overrides))
    if specs:
        faults = [parse_fault_spec(s, array) for s in specs]
        block = FaultInjector(faults, array, seed=seed, t0_ns=int(block.t_ns[0])).apply_block(block)
    return array, block


def far_bound(n_samples: int, level: float, window: int, z: float = 3.1) -> float:
    """Upper 99.9 % bound on the alarm count of n samples at a per-sample rate ``level``.

    Alarms of a windowed test come in clumps no longer than the window: the variance of
    the count is at most ``window`` times the binomial one, so the normal bound is
    ``n p + z sqrt(window n p (1 - p))``.
    """
    mean = n_samples * level
    return mean + z * np.sqrt(window * mean * (1.0 - level))


def test_clipped_square_moments_are_the_chi_square_ones_without_clipping():
    mean, variance, lag1 = clipped_square_moments(1e3)
    assert_allclose((mean, variance, lag1), (1.0, 2.0, 0.5), atol=1e-9)


def test_clipped_square_moments_match_simulated_differences():
    """Moments of min(z^2, 9) for differenced white noise; 6-sigma Monte Carlo tolerances."""
    rng = np.random.default_rng(5)
    z = np.diff(rng.standard_normal(400_001)) / np.sqrt(2.0)
    q = np.minimum(z**2, 9.0)
    mean, variance, lag1 = clipped_square_moments(3.0)
    n = q.size
    # Var of the sample mean of a lag-1 dependent sequence: (v + 2 c1) / n
    assert abs(q.mean() - mean) < 6 * np.sqrt((variance + 2 * lag1) / n)
    centred = q - mean
    assert abs(np.mean(centred**2) - variance) < 6 * np.sqrt(np.var(centred**2) * 3 / n)
    products = centred[1:] * centred[:-1]
    assert abs(products.mean() - lag1) < 6 * np.sqrt(np.var(products) * 3 / n)


def test_robust_scale_ignores_isolated_outliers():
    rng = np.random.default_rng(6)
    d = np.diff(rng.standard_normal((2001, 3)), axis=0)  # Var d = 2
    d[::97, :] += 15.0  # 21 gross outliers per column
    mean, variance, lag1 = clipped_square_moments(3.0)
    tau = robust_scale(d, 3.0, mean)
    # 2000 differences of white noise: relative sd of tau <= sqrt(2 / nu_2000); allow 4 sd
    tolerance = 4 * np.sqrt(2 / equivalent_dof(np.array([2000]), (mean, variance, lag1))[0])
    assert_allclose(tau, 2.0, rtol=tolerance + 0.03)  # + the outliers' bounded pull
    assert np.mean(d**2, axis=0).min() > 4.0  # the plain variance would be ruined


@pytest.mark.parametrize(
    "specs",
    [
        ("step:imu0.gyro.x,at=5s,amp=0.9deg/s",),
        ("drift:imu0.gyro.x,at=2s,rate=0.05deg/s/min", "drift:imu5.gyro.z,at=2s,rate=3deg/s/min"),
    ],
    ids=["step 0.9 deg/s", "bias drift"],
)
def test_bias_step_or_drift_is_not_a_noise_alarm(specs):
    """A mean change is not noise growth (the old statistic alarmed until the end)."""
    detector = make()
    total, alarms = 0, 0
    for seed in (3, 4):
        array, block = paper_table4(seed, specs, outliers=False, duration=20.0)
        out = run(detector, array, block)["gyro"]
        after = block.t_s() >= 2.0
        total += int(after.sum())
        alarms += int(out.alarm[after].sum())
    assert alarms <= far_bound(total, 1.5 * detector.alpha, detector.window_samples)


def test_level_holds_on_paper_table4_with_its_outliers():
    """Gyro outliers (p = 0.001, +-1 deg/s) do not count as noise growth (old FAR 13-23 %).
    One run per seed serves both sensor types (simulating and running both seeds again per
    type would give the same rows at twice the CPU)."""
    detector = make()
    total = {"gyro": 0, "accel": 0}
    alarms = {"gyro": 0, "accel": 0}
    for seed in (3, 4):
        array, block = paper_table4(seed, duration=20.0)
        out = run(detector, array, block)
        after = block.t_s() >= 2.0
        for sensor_type in total:
            total[sensor_type] += int(after.sum())
            alarms[sensor_type] += int(out[sensor_type].alarm[after].sum())
    for sensor_type in total:
        bound = far_bound(total[sensor_type], 1.5 * detector.alpha, detector.window_samples)
        assert alarms[sensor_type] <= bound, sensor_type


# --- the level of each log, not only on average over calibrations ----------------


@functools.lru_cache(maxsize=4)
def calibration_scales(n_windows: int, count: int, seed: int, outliers: float = 0.0):
    """Robust scales of ``n_windows`` independent calibration windows of white noise.

    Each window has ``count + 1`` samples of unit variance (``count`` differences, true
    tau = Var d = 2); a share ``outliers`` of the samples gets +-6.7 sigma added (the
    paper-table4 gyro outliers). Cached (read-only): the dof test and the white coverage
    test read the same 20 000 draws of seed 12 (0.3-0.5 s of CPU each).
    """
    rng = np.random.default_rng(seed)
    samples = rng.standard_normal((count + 1, n_windows))
    hit = rng.random(samples.shape) < outliers
    samples += np.where(hit, rng.choice([-6.7, 6.7], size=samples.shape), 0.0)
    scales = robust_scale(np.diff(samples, axis=0), 3.0, clipped_square_moments(3.0)[0])
    scales.setflags(write=False)
    return scales


# Monte Carlos over 20 000 calibration windows (statistical, rule 1 of docs/testing.md):
# scale_estimator_dof and calibration_factor keep their default test in
# test_threshold_is_the_known_variance_quantile_raised_by_the_calibration_factor and the
# detector's fits.
@pytest.mark.slow  # 0.5-0.7 s of CPU with the 20 000 windows
def test_scale_estimator_dof_matches_simulated_calibrations():
    """Var(ln tau_hat) = 2 / nu_cal for the 2 s window (199 differences). The draws are
    the white coverage test's (seed 12; seed 11 before). Over seeds 0-19 the first
    deviation was 0.1-1.9 sd (bound 5) and the earlier dof's 3.8-6.6 sd (bound 3)."""
    log_tau = np.log(calibration_scales(20_000, 199, seed=12, outliers=0.0) / 2.0)
    measured = log_tau.var()
    # sd of a sample variance: sqrt((m4 - s^4) / M), from the draws themselves; 5 sd
    centred = log_tau - log_tau.mean()
    sd = np.sqrt((np.mean(centred**4) - measured**2) / log_tau.size)
    expected = 2.0 / scale_estimator_dof(199, 3.0)
    assert abs(measured - expected) < 5 * sd
    # the test resolves the earlier dof (that of the mean of q, 5 % fewer: the
    # clipped-scale estimator's derivative was left out)
    earlier = 2.0 / equivalent_dof(np.array([199]), clipped_square_moments(3.0))[0]
    assert abs(measured - earlier) > 3 * sd


@pytest.mark.slow  # 0.3-0.5 s of CPU per case
@pytest.mark.parametrize("outliers", [0.0, 0.001], ids=["white", "paper-table4 outliers"])
def test_calibration_factor_covers_the_true_scale_with_the_stated_confidence(outliers):
    """P(tau_hat * factor >= tau) = level_confidence over calibrations (binomial, 5 sd)."""
    n_windows = 20_000
    tau = calibration_scales(n_windows, 199, seed=12, outliers=outliers)
    for confidence in (0.9, DEFAULT_LEVEL_CONFIDENCE, 0.99):
        factor = calibration_factor(scale_estimator_dof(199, 3.0), confidence)
        covered = np.mean(tau * factor >= 2.0)
        sd = np.sqrt(confidence * (1 - confidence) / n_windows)
        assert covered > confidence - 5 * sd
        if not outliers:  # outliers pull tau_hat up a little (+1.7 %): more coverage
            assert covered < confidence + 5 * sd


def test_short_calibration_window_warns_with_its_dof_and_the_window_that_would_do():
    array, block = wearable12(0, factor=None)
    t = block.t_s()
    short = make()
    short.fit(block.mask(t < 0.8), array)  # 80 samples
    messages = short.calibration_warnings()
    assert len(messages) == 2  # gyro and accel
    assert "degrees of freedom" in messages[0] and "--calibrate" in messages[0]
    factor = short.models["gyro"].calibration_factor
    assert factor > 1.25 and f"{factor:.2f}x" in messages[0]
    long = make()
    long.fit(block.mask(t < 10.0), array)
    assert long.calibration_warnings() == []
    assert long.models["gyro"].calibration_factor < factor


# --- healthy noise spread (ArrayConfig <type>_noise_spread) ------------------------------

SPREAD_RATE = 100.0


def static_gyro_log(sigma: np.ndarray, seed: int, seconds: float = 100.0, calibrate_s: float = 10.0,
                    grow: np.ndarray | None = None):  # fmt: skip
    """4 co-aligned IMUs at rest, gyros only: white noise of per-sensor sigma (12,) rad/s for
    the first ``calibrate_s`` and ``sigma * grow`` after."""
    array = ArrayConfig.co_aligned(4, SPREAD_RATE, sensors=("gyro",))
    rng = np.random.default_rng(seed)
    n, n_cal = int(seconds * SPREAD_RATE), int(calibrate_s * SPREAD_RATE)
    scale = np.tile(sigma, (n, 1))
    if grow is not None:
        scale[n_cal:] *= grow
    gyro = (scale * rng.standard_normal((n, 12))).reshape(n, 4, 3)
    t_ns = (np.arange(n) * 1e9 / SPREAD_RATE).astype(np.int64)
    return array, ImuBlock(t_ns=t_ns, gyro=gyro)


def with_spread(array: ArrayConfig, kappa: float) -> ArrayConfig:
    return array.with_noise_spread([{"gyro": np.full(3, kappa)} for _ in range(array.n_imus)])


def test_residual_spread_is_the_weighted_mean_of_the_sensor_spreads():
    array = ArrayConfig.co_aligned(4, SPREAD_RATE, sensors=("gyro",))
    operator, _ = leave_one_out_operator(array.measurement_matrix("gyro"))
    assert_allclose(residual_spread(operator, np.full(12, 2.5), None), 2.5, rtol=1e-12)
    # co-aligned x axes: r_0 = m_0 - mean(m_3, m_6, m_9), weights 1 and 1/9 each
    kappa = np.ones(12)
    kappa[0] = 3.0
    spread = residual_spread(operator, kappa, None)
    assert_allclose(spread[0], (3.0 + 3 / 9) / (1 + 3 / 9), rtol=1e-12)
    assert_allclose(spread[3], (1.0 + 3.0 / 9 + 2 / 9) / (1 + 3 / 9), rtol=1e-12)
    assert_allclose(spread[1], 1.0, rtol=1e-12)
    sigma = np.ones(12)
    sigma[3] = 2.0  # a noisier neighbour weighs 4x in residual 0
    assert_allclose(residual_spread(operator, kappa, sigma)[0], (3.0 + 6 / 9) / (1 + 6 / 9))


def test_without_the_field_or_with_noise_spread_false_the_detector_is_unchanged():
    # 14 s, the noise growth from 12 s: the claims are equalities, so a short log suffices
    array, block = wearable12(seed=2)
    block = block.slice(0, 1400)
    plain = run(make(), array, block)
    spread_array = array.with_noise_spread(
        [{s: np.full(3, 2.0) for s in ("gyro", "accel")} for _ in range(array.n_imus)]
    )
    off = run(make({"noise_spread": False}), spread_array, block)
    on = run(make(), spread_array, block)
    for sensor_type in plain:
        for name in ("statistic", "threshold", "alarm", "isolated", "amplitude", "scores"):
            a, b = getattr(plain[sensor_type], name), getattr(off[sensor_type], name)
            assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), name
        assert not np.array_equal(plain[sensor_type].statistic, on[sensor_type].statistic)
    assert plain["accel"].alarm[1250:].any()  # rows with alarms are among those compared
    detector = make()
    detector.fit(block.slice(0, 200), array)
    assert "noise_spread" not in detector.metadata()["types"]["accel"]


def predicted_rate(stats, model, ratio: float) -> tuple[float, float]:
    """Per-sample alarm probability of a full window (no clipping) when the residual's
    variance is ``ratio`` times the tested scale, for the calibrated scale at the edges of
    its 99.9 % interval (tau_hat / tau ~ chi2(nu_cal) / nu_cal): ``P(u > u_c)`` with
    ``u ~ ratio (tau / tau_hat) chi2(nu_k) / nu_k`` (``stats``: scipy.stats)."""
    nu, nu_cal = model.dof[-1], model.calibration_dof
    lo, hi = stats.chi2.ppf([0.0005, 0.9995], nu_cal) / nu_cal  # tau_hat / tau
    u_c = model.critical_ratio[-1]
    # a high tau_hat lowers u: the low end of the rate comes from the high end of tau_hat
    return float(stats.chi2.sf(u_c * hi / ratio * nu, nu)), float(
        stats.chi2.sf(u_c * lo / ratio * nu, nu)
    )


def test_one_sided_spread_test_holds_its_level_at_the_boundary_and_keeps_power_beyond(scipy_stats):
    """Null boundary: every gyro's sigma grows by sqrt(kappa) after the calibration window
    (variance x kappa = 2.25); with the spread in the array the level is at most alpha
    (99.9 % clumped-binomial bound, ``far_bound``), without it the same log alarms far
    more. Beyond: one gyro's sigma x3 (variance x9) from 10 s: the LOO residual's variance
    is ``1 + 8 (1 - P_jj)`` = 7 times the calibrated one, 7 / 2.25 over the null boundary;
    its per-sample detection rate lies within the rates predicted at the edges of the
    calibrated scale's 99.9 % interval (Satterthwaite chi-square, no clipping), minus a
    4-sigma clumped-binomial margin."""
    kappa = 2.25
    params = {"alpha": 0.01, "clip": 1000.0}
    sigma = np.full(12, 0.002)
    array, block = static_gyro_log(sigma, seed=5, grow=np.full(12, np.sqrt(kappa)))
    after = block.t_s() >= 10.0
    det = make(params)
    out = run(det, with_spread(array, kappa), block, calibrate=(0.0, 10.0))["gyro"]
    n = int(after.sum())
    assert out.alarm[after].sum() <= far_bound(n, det.alpha, det.window_samples)
    plain = run(make(params), array, block, calibrate=(0.0, 10.0))["gyro"]
    assert plain.alarm[after].mean() > 0.5  # the spread is what keeps the level
    grow = np.ones(12)
    grow[4] = 3.0
    array, block = static_gyro_log(sigma, seed=6, grow=grow)
    det = make(params)
    out = run(det, with_spread(array, kappa), block, calibrate=(0.0, 10.0))["gyro"]
    model = det.models["gyro"]
    full = after & (np.arange(len(after)) >= 1000 + det.window_samples)
    rate = out.alarm[full].mean()
    lo, hi = predicted_rate(scipy_stats, model, 7.0 / kappa)
    margin = 4 * np.sqrt(det.window_samples * 0.25 / full.sum())
    assert lo - margin <= rate <= hi + margin
    assert (out.isolated[full & out.alarm] == 4).all()
    assert_allclose(np.median(out.amplitude[full & out.alarm]), np.sqrt(7.0), rtol=0.25)
    # the price: without the spread the same fault is detected at the higher predicted rate
    plain = run(make(params), array, block, calibrate=(0.0, 10.0))["gyro"]
    assert plain.alarm[full].mean() > rate


# --- under a false-alarm budget ----------------------------------------------------------


BUDGET = {"false_alarms": "1/h"}


def test_a_budget_refuses_the_per_sample_options():
    for raw in (
        {"window": "0.3s"},
        {"release": "0"},
        {"release_window": "0.2s"},
        {"clip": "4"},
        {"level_confidence": "0.5"},
    ):
        with pytest.raises(DetectorConfigError, match="per-sample test"):
            make({**BUDGET, **raw})


def test_a_budget_detects_and_isolates_a_noise_growth_fast():
    # x3 on imu0.accel.x from 12 s: the residual's variance x7.7; the optimal test's delay
    # at 1/h (Lorden) is ~7 terms, ~0.1 s; the threshold still learning the variance
    # (calibrated on 2 s) costs a little
    array, block = wearable12(100)
    det = make(BUDGET)
    out = run(det, array, block)["accel"]
    t = block.t_s()
    assert not out.alarm[t < 12.0].any()
    first = t[np.flatnonzero(out.alarm)[0]]
    assert 12.0 <= first <= 12.4
    during = out.alarm & (t >= 12.0) & (t < 18.0)
    assert during.sum() > 0.95 * np.count_nonzero((t >= first) & (t < 18.0))
    assert np.all(out.isolated[during] == 0)  # imu0.accel.x
    assert_allclose(np.nanmedian(out.amplitude[during]), np.sqrt(7.7), rtol=0.2)
    # the alarm ends within a second of the fault, and the threshold is the bank's
    assert not out.alarm[t > 19.0].any()
    meta = det.metadata()["types"]["accel"]["budget"]
    assert meta["false_alarms_per_hour"] == pytest.approx(1.0)
    assert meta["hypotheses"] == 36 * 2
    assert out.threshold[-1] == pytest.approx(meta["threshold_schedule"]["threshold"][-1], abs=1.5)
    assert 0.05 < meta["lorden_delay_x3_s"][0] < 0.2


def test_a_budget_holds_on_a_fault_free_minute_with_outliers_and_ignores_a_bias_step():
    array, block = simulate_block(preset("paper-table4", seed=3, duration=60.0))
    det = make(BUDGET)
    out = run(det, array, block, block_size=997)
    assert not out["gyro"].alarm.any() and not out["accel"].alarm.any()
    meta = det.metadata()["types"]["gyro"]["budget"]
    assert meta["outlier_share"] > 0  # paper-table4's gyro outliers, seen in calibration
    assert meta["seconds_beyond_the_noise_model"] == 0
    json.dumps(det.metadata())
    assert det.calibration_warnings() == []
    # a bias step (0.9 deg/s, 6 sigma) is not a noise growth: the contrasts drop the mean
    # and the winsorizer bounds the step's transient to about one term at the clip
    fault = parse_fault_spec("step:imu3.gyro.y,at=20s,amp=0.9deg/s", array)
    stepped = FaultInjector([fault], array, seed=3, t0_ns=int(block.t_ns[0])).apply_block(block)
    assert not run(make(BUDGET), array, stepped)["gyro"].alarm.any()


def test_budget_rows_do_not_depend_on_the_block_size():
    array, block = wearable12(101, factor=2.0, duration=20.0)
    a = run(make(BUDGET), array, block, block_size=97)
    b = run(make(BUDGET), array, block, block_size=1024)
    for sensor_type in a:
        assert_allclose(a[sensor_type].statistic, b[sensor_type].statistic, rtol=1e-9, atol=1e-9)
        np.testing.assert_array_equal(a[sensor_type].alarm, b[sensor_type].alarm)
        np.testing.assert_array_equal(a[sensor_type].isolated, b[sensor_type].isolated)


def test_a_budget_widens_the_test_in_motion_by_the_jitter_model_and_warns_beyond_it():
    # a static array whose gyros' noise is x3 in a "motion" stretch on every sensor: with a
    # jitter model that knows it (A_t = 8 there) the bank holds; without one, detect warns
    # that most residuals exceed the calibrated noise (the budget does not hold there)
    rng = np.random.default_rng(11)
    array = ArrayConfig.co_aligned(6, 100.0, sensors=("gyro",))
    n = 6000
    values = 0.01 * rng.standard_normal((n, 18))
    values[3000:4000] *= 3.0
    block = ImuBlock(t_ns=np.arange(n) * 10_000_000, gyro=values.reshape(n, 6, 3))
    det = make({**BUDGET, "types": "gyro"})
    out = run(det, array, block)["gyro"]
    assert out.alarm[3000:4000].any()
    notes = det.calibration_warnings()
    assert len(notes) == 1 and "most leave-one-out residuals" in notes[0]
    assert "budget does not hold" in notes[0] and "\n" not in notes[0]
    model = det.models["gyro"]
    factors = np.where((np.arange(n) >= 3000) & (np.arange(n) < 4000), 9.0, 1.0)
    budget = model.budget
    budget.fit(det._residuals("gyro", model, block.slice(0, 200)))
    residuals = det._residuals("gyro", model, block)
    widened = budget.process(residuals, factors)
    assert not widened.alarm.any()
    assert budget.check.flagged == 0


def test_a_budget_reads_the_arrays_jitter_model_unless_told_not_to():
    array, block = wearable12(102, factor=None, duration=5.0)
    noisy = array.with_sensor_noise(
        [{"gyro": np.full(3, 0.0017), "accel": np.full(3, 0.03)} for _ in range(12)]
    ).with_jitter({"accel": 0.002})
    det = make(BUDGET)
    run(det, noisy, block)
    assert det.models["accel"].inflation is not None and det.models["gyro"].inflation is None
    assert det.metadata()["types"]["accel"]["budget"]["jitter_s"] == 0.002
    det = make({**BUDGET, "jitter": "false"})
    run(det, noisy, block)
    assert det.models["accel"].inflation is None
    per_sample = make()  # the per-sample test never reads it (its figures unchanged)
    run(per_sample, noisy, block)
    assert per_sample.models["accel"].inflation is None


@pytest.mark.slow
@pytest.mark.parametrize("name", ["paper-table4", "conical6", "wearable12"])
def test_a_budget_of_one_an_hour_holds_for_an_hour_on_each_preset(name):
    """An hour of each preset (development seed 36; calibration 0-2 s, 5 s for conical6's
    static start): the bank is designed for half the budget; measured 0-0.5/h per channel on
    the tuning seeds. At most 3 episodes per channel (Poisson(1) gives 3 or more with
    probability 8 %, at the budget itself)."""
    from imufdi_cli.simulate import config_from_options, simulate

    config = config_from_options(name, seed=36, duration="3600s")
    array, blocks = simulate(config, block_size=4096)
    det = make(BUDGET)
    calibration = 500 if name == "conical6" else 200
    first = next(blocks)
    det.fit(first.slice(0, calibration), array)
    counts: dict[str, int] = {}
    last: dict[str, bool] = {}
    for b in [first.slice(calibration, len(first)), *blocks]:
        for sensor_type, out in det.process(b).items():
            alarm = out.alarm
            before = np.concatenate([[last.get(sensor_type, False)], alarm[:-1]])
            counts[sensor_type] = counts.get(sensor_type, 0) + int(np.sum(alarm & ~before))
            last[sensor_type] = bool(alarm[-1]) if alarm.size else last.get(sensor_type, False)
    assert counts and all(count <= 3 for count in counts.values()), counts
    assert det.calibration_warnings() == []


def test_a_budget_beyond_the_sample_rate_is_refused_at_fit():
    array, block = wearable12(104, factor=None, duration=3.0)
    det = make({"false_alarms": "100/s"})
    with pytest.raises(DetectorConfigError, match="not below 3/4 of the sample rate"):
        run(det, array, block)
