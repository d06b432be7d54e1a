"""Sampling-time jitter model: analytic factors, fits, and the level of glt/pca-parity in motion."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from imufdi_cli.array import ArrayConfig
from imufdi_cli.detectors.base import parse_params
from imufdi_cli.detectors.glt import GltDetector
from imufdi_cli.detectors.pca_parity import PcaParityDetector
from imufdi_cli.errors import ArrayConfigError, ImufdiError
from imufdi_cli.log import ImuBlock
from imufdi_cli.maths.jitter import (
    MAX_JITTER_S,
    MotionInflation,
    array_inflation,
    consensus_projector,
    fit_jitter,
    minimum_detectable_step,
)
from imufdi_cli.tomlfile import parse_toml

RATE = 100.0
DT_NS = 10_000_000
SIGMA = 0.01  # rad/s


def skewed_array(m: int = 6, jitter: float = 0.0) -> ArrayConfig:
    """m co-located gyro triads with distinct rotations (no lever arms), per-sensor noise."""
    rng = np.random.default_rng(11)
    rows = []
    for _ in range(m):
        q = rng.standard_normal(4)
        rows.append({"quaternion": list(q / np.linalg.norm(q)), "accel_axes": ""})
    data = {"rate_hz": RATE, "noise": {"gyro": SIGMA}, "imu": rows}
    if jitter:
        data["jitter"] = {"gyro": jitter}
    return ArrayConfig.from_dict(data)


def moving_gyro(
    array: ArrayConfig, n: int, rng: np.random.Generator, jitter: float, start: int = 0
) -> tuple[ImuBlock, np.ndarray]:
    """Gyro triads under a fast rotation, with white noise SIGMA and, in whitened units, the
    isotropic jitter term of the model: extra N(0, jitter^2 e_t) per sensor, e_t from the
    true rate of change of the consensus prediction. Returns the block and the true e_t."""
    t = (start + np.arange(n)) / RATE
    w = np.stack(
        [20 * np.sin(2 * np.pi * 0.9 * t), 15 * np.cos(2 * np.pi * 1.3 * t), 10 * np.sin(t)], 1
    )
    w_dot = np.stack(
        [
            20 * 2 * np.pi * 0.9 * np.cos(2 * np.pi * 0.9 * t),
            -15 * 2 * np.pi * 1.3 * np.sin(2 * np.pi * 1.3 * t),
            10 * np.cos(t),
        ],
        1,
    )
    H = array.measurement_matrix("gyro")
    n_s = H.shape[0]
    energy = np.einsum("ij,ij->i", w_dot @ H.T, w_dot @ H.T) / SIGMA**2 / n_s  # |ydot_w|^2/n
    extra = jitter * np.sqrt(energy)[:, None] * rng.standard_normal((n, n_s))
    values = w @ H.T + SIGMA * (rng.standard_normal((n, n_s)) + extra)
    gyro = values.reshape(n, array.n_imus, 3)
    return ImuBlock(t_ns=(start + np.arange(n)) * DT_NS, gyro=gyro), energy


# --- the factor ------------------------------------------------------------------------


def test_factor_of_a_noise_free_ramp_is_analytic_and_streams():
    """m_w = H_w (x0 + a t): dm_w/dt = H_w a exactly, so 1 + A = 1 + s^2 (|H_w a|^2 -
    2 c / dt^2) / n (c = 3), the first sample 1; blocks give the same factors as one run."""
    array = skewed_array()
    H = array.measurement_matrix("gyro")
    sigma = np.full(H.shape[0], SIGMA)
    a = np.array([3.0, -1.0, 2.0])
    t_ns = np.arange(50) * DT_NS
    values = (np.array([0.1, 0.2, 0.3]) + (t_ns[:, None] * 1e-9) * a) @ H.T
    jitter = 1e-3
    inflation = MotionInflation(H / SIGMA, sigma, jitter, RATE)
    got = inflation.factors(values, t_ns)
    hw_a = H @ a / SIGMA
    expected = 1 + jitter**2 * (hw_a @ hw_a - 2 * 3 * RATE**2) / H.shape[0]
    assert got[0] == 1.0
    assert_allclose(got[1:], expected, rtol=1e-9)
    split = MotionInflation(H / SIGMA, sigma, jitter, RATE)
    parts = np.concatenate(
        [split.factors(values[:17], t_ns[:17]), split.factors(values[17:], t_ns[17:])]
    )
    assert_allclose(parts, got, rtol=1e-12)
    # window: the mean of the per-sample factors over the last w samples
    windowed = MotionInflation(H / SIGMA, sigma, jitter, RATE, window=4)
    w_got = np.concatenate(
        [windowed.factors(values[:3], t_ns[:3]), windowed.factors(values[3:], t_ns[3:])]
    )
    manual = [got[max(0, i - 3) : i + 1].mean() for i in range(len(got))]
    assert_allclose(w_got, manual, rtol=1e-12)


def test_factor_at_rest_is_near_one_and_invalid_rows_do_not_propagate():
    """White noise only: the noise part 2c/dt^2 is removed, E[A] is small (clipped at 0);
    a NaN sample gives factor 1 on its row and the next one, not NaN."""
    array = skewed_array()
    H = array.measurement_matrix("gyro")
    rng = np.random.default_rng(5)
    values = SIGMA * rng.standard_normal((4000, H.shape[0]))
    inflation = MotionInflation(H / SIGMA, np.full(H.shape[0], SIGMA), 1e-3, RATE)
    factors = inflation.factors(values, np.arange(4000) * DT_NS)
    # A = s^2 max(0, |F dn|^2 - 6/dt^2)/n, |F dn|^2 ~ 2 chi2(3)/dt^2: mean of the positive
    # part of 2/dt^2 (chi2(3) - 3) is 2/dt^2 * 1.19 -> E[A] = 1e-6 * 2e4 * 1.19 / 18 ~ 1.3e-3
    assert 1.0 <= factors.min() and factors.mean() < 1.005
    values[100, 2] = np.nan
    factors = MotionInflation(H / SIGMA, np.full(H.shape[0], SIGMA), 1e-3, RATE).factors(
        values, np.arange(4000) * DT_NS
    )
    assert np.all(np.isfinite(factors)) and factors[100] == 1.0 and factors[101] == 1.0


def test_minimum_detectable_step_matches_the_noncentral_chi2(scipy_stats):
    dof, alpha = 21, 0.01
    step = minimum_detectable_step(0.875, dof, alpha)
    threshold = scipy_stats.chi2.ppf(1 - alpha, dof)
    assert scipy_stats.ncx2.sf(threshold, dof, step**2 * 0.875) == pytest.approx(0.5, abs=1e-6)
    # the widening multiplies the step by sqrt(1 + A)
    assert minimum_detectable_step(0.875, dof, alpha, 400.0) == pytest.approx(20 * step)


# --- fits ------------------------------------------------------------------------------


def test_fits_recover_the_jitter_of_data_drawn_from_the_model():
    """Data drawn from the model with sigma_t = 0.5 ms. Moments: the estimate of s^2 is a
    ratio of sums; Var(D_t) = 2 q (1 + A_t)^2 gives its standard error, and the test allows
    5 of them. Level: the quantile fit of the same data agrees within the same margin."""
    array = skewed_array()
    rng = np.random.default_rng(21)
    block, energy = moving_gyro(array, 20000, rng, 5e-4)
    H = array.measurement_matrix("gyro")
    white = array.select(block.gyro, "gyro") / SIGMA
    rows = np.ones(len(block), dtype=bool)
    t_s = block.t_s()
    q = H.shape[0] - 3
    moments = fit_jitter(H / SIGMA, white, t_s, rows)
    A = (5e-4) ** 2 * energy[1:]
    se_s2 = math.sqrt(np.sum(2 * q * (1 + A) ** 2)) / (q * np.sum(energy[1:]))
    assert abs(moments**2 - 25e-8) < 5 * se_s2
    level = fit_jitter(H / SIGMA, white, t_s, rows, alpha=0.01)
    assert abs(level**2 - 25e-8) < 0.25 * 25e-8
    # no motion excess: nothing fitted
    still = SIGMA * rng.standard_normal(white.shape) / SIGMA
    assert fit_jitter(H / SIGMA, still, t_s, rows, alpha=0.01) == 0.0
    # at rest, a residual no motion explains (a 50 sigma offset on one sensor, not
    # removed): no sigma_t holds the level, the fit says so by returning its cap
    still[:, 4] += 50.0
    assert fit_jitter(H / SIGMA, still, t_s, rows, alpha=0.01) == MAX_JITTER_S


# --- detectors -------------------------------------------------------------------------


def _glt(**raw: object) -> GltDetector:
    return GltDetector(**parse_params(GltDetector.PARAMS, dict(raw), "glt"))


def test_no_jitter_is_bit_identical_and_jitter_divides_the_statistics():
    """sigma_t = 0 (or glt.jitter=false) leaves glt unchanged to the bit; with sigma_t the
    statistic and the isolation scores are the plain ones divided by 1 + A_t."""
    rng = np.random.default_rng(3)
    plain_array = skewed_array()
    block, _ = moving_gyro(plain_array, 3000, rng, 5e-4)
    calibration = block.slice(0, 500)

    def run(array: ArrayConfig, **raw: object):
        det = _glt(sigma_source="config", **raw)
        det.fit(calibration, array)
        return det.process(block)["gyro"]

    plain = run(plain_array)
    zero = run(plain_array.with_jitter({"gyro": 0.0}))
    off = run(skewed_array(jitter=5e-4), jitter="false")
    for other in (zero, off):
        for name in ("statistic", "threshold", "alarm", "isolated", "scores"):
            assert_array_equal(getattr(other, name), getattr(plain, name))
    jittered = run(skewed_array(jitter=5e-4))
    H = plain_array.measurement_matrix("gyro")
    factors = MotionInflation(H / SIGMA, np.full(H.shape[0], SIGMA), 5e-4, RATE).factors(
        plain_array.select(block.gyro, "gyro"), block.t_ns
    )
    assert_allclose(jittered.statistic, plain.statistic / factors, rtol=1e-12)
    assert_allclose(jittered.scores, plain.scores / factors[:, None], rtol=1e-12)
    assert_array_equal(jittered.alarm, jittered.statistic > jittered.threshold)


def test_glt_holds_its_level_in_motion_with_the_jitter_model(scipy_stats):
    """Fast rotation with the model's jitter (sigma_t = 0.5 ms): without the model glt
    alarms on most samples; with the fitted sigma_t (on another stretch) it holds alpha.
    Bound: binomial 99.9 % upper quantile of alpha over the samples, widened for the
    estimated sigma_t (fitted on 10,000 samples: relative error of a few %)."""
    rng = np.random.default_rng(8)
    array = skewed_array()
    train, _ = moving_gyro(array, 10000, rng, 5e-4)
    test, _ = moving_gyro(array, 10000, rng, 5e-4, start=10000)
    H = array.measurement_matrix("gyro")
    white = array.select(train.gyro, "gyro") / SIGMA
    fitted = fit_jitter(H / SIGMA, white, train.t_s(), np.ones(len(train), bool), alpha=0.01)
    calibration = test.slice(0, 300)
    plain = _glt(sigma_source="config")
    plain.fit(calibration, array)
    plain_rate = plain.process(test)["gyro"].alarm[300:].mean()
    assert plain_rate > 0.3
    det = _glt(sigma_source="config")
    det.fit(calibration, array.with_jitter({"gyro": fitted}))
    rate = det.process(test)["gyro"].alarm[300:].mean()
    n = 9700
    assert rate <= 1.5 * scipy_stats.binom.ppf(0.999, n, 0.01) / n
    assert det.metadata()["types"]["gyro"]["jitter_s"] == pytest.approx(fitted)


def test_pca_parity_hook_divides_by_the_window_mean_factor():
    rng = np.random.default_rng(4)
    plain_array = skewed_array()
    block, _ = moving_gyro(plain_array, 2000, rng, 5e-4)
    calibration = block.slice(0, 400)

    def run(array: ArrayConfig):
        det = PcaParityDetector(types="gyro")
        det.fit(calibration, array)
        return det.process(block)["gyro"]

    plain = run(plain_array)
    assert_array_equal(run(plain_array.with_jitter({"gyro": 0.0})).statistic, plain.statistic)
    jittered = run(skewed_array(jitter=5e-4))
    inflation = array_inflation(
        plain_array.with_jitter({"gyro": 5e-4}), "gyro", plain_array.measurement_matrix("gyro"),
        window=round(0.2 * RATE),
    )  # fmt: skip
    assert inflation is not None
    factors = inflation.factors(plain_array.select(block.gyro, "gyro"), block.t_ns)
    assert_allclose(jittered.statistic, plain.statistic / factors, rtol=1e-12)


def test_consensus_projector_is_the_hat_matrix():
    H = skewed_array().measurement_matrix("gyro")
    F = consensus_projector(H)
    assert_allclose(F @ H, H, atol=1e-12)
    assert np.trace(F) == pytest.approx(3.0)


# --- config ----------------------------------------------------------------------------


def test_jitter_in_toml_round_trips_with_units_and_bad_values_are_refused():
    base = skewed_array().to_dict()
    array = ArrayConfig.from_dict({**base, "jitter": {"gyro": "0.3ms", "accel": 0.001}})
    assert array.jitter == {"gyro": pytest.approx(3e-4), "accel": 0.001}
    again = ArrayConfig.from_dict(parse_toml(array.to_toml(), "round trip", ImufdiError))
    assert again.jitter == array.jitter and again == array
    assert ArrayConfig.from_json(array.to_json()).jitter == array.jitter
    for bad, message in (
        ({"gyro": -1.0}, r"jitter\.gyro: must be finite and >= 0"),
        ({"gyro": "nan"}, r"jitter\.gyro"),
        ({"gyro": "3deg/s"}, r"jitter\.gyro"),
        ({"wheel": 0.001}, "unknown sensor type"),
    ):
        with pytest.raises(ArrayConfigError, match=message):
            ArrayConfig.from_dict({**base, "jitter": bad})
    with pytest.raises(ArrayConfigError, match=r"jitter\.gyro"):
        skewed_array().with_jitter({"gyro": float("inf")})
