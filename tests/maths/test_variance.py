"""maths.variance and maths.contrasts: run lengths, thresholds, Helmert contrasts, the
winsorizer and the bank."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from imufdi_cli.maths.contrasts import HelmertContrasts, Winsorizer
from imufdi_cli.maths.sequential import NO_ISOLATION, NOT_ISOLABLE
from imufdi_cli.maths.variance import (
    VarianceCusumBank,
    VarianceDesign,
    lorden_variance_terms,
    threshold_schedule,
    variance_false_alarm_rate,
    variance_increments,
    variance_information,
    variance_run_length,
    variance_threshold,
)

RATE_HZ = 100.0


def _simulated_run_length(
    ratio: float, clip: float, h: float, rng: np.random.Generator, chains: int = 20_000
) -> tuple[float, float]:
    """Mean and standard error of the run length of one CUSUM (1)-(2) from 0."""
    state = np.zeros(chains)
    length = np.zeros(chains)
    open_ = np.ones(chains, bool)
    while open_.any():
        z = rng.standard_normal(open_.sum())
        state[open_] = np.maximum(0.0, state[open_] + variance_increments(ratio, clip, z))
        length[open_] += 1
        open_[open_] = state[open_] <= h
    return float(length.mean()), float(length.std() / math.sqrt(chains))


@pytest.mark.parametrize(
    ("ratio", "clip", "h"), [(9.0, 4.0, 4.0), (3.0, 4.0, 3.0), (9.0, 10.0, 5.0)]
)
def test_run_length_of_the_chain_matches_a_simulation(ratio: float, clip: float, h: float) -> None:
    # 20,000 simulated runs: the mean's standard error is ~0.7 %; the chain's cell-centre
    # discretisation is within ~1.5 % of it at 100 states (measured on these designs)
    mean, se = _simulated_run_length(ratio, clip, h, np.random.default_rng(int(ratio * h)))
    chain = variance_run_length(ratio, clip, h)
    assert abs(chain - mean) < 4.0 * se + 0.02 * mean


def test_sigma_errors_and_outliers_shorten_the_run_length() -> None:
    base = variance_run_length(9.0, 4.0, 8.0)
    assert variance_run_length(9.0, 4.0, 8.0, scale=1.05) < base
    assert variance_run_length(9.0, 4.0, 8.0, contamination=1e-3) < base
    assert variance_run_length(9.0, 4.0, 9.0) > base
    # a growth of the design's size: the mean delay is short (here ~8 terms)
    assert variance_run_length(9.0, 4.0, 8.0, scale=3.0) < 12


@pytest.mark.parametrize("per_hour", [1.0, 360.0])
def test_the_threshold_meets_the_rate_asked(per_hour: float) -> None:
    design = VarianceDesign()
    per_term = per_hour / 3600.0 / (0.75 * RATE_HZ)
    h = variance_threshold(design, 12, per_term, 2.0 / 500.0, 1e-4)
    assert variance_false_alarm_rate(design, 12, h, 2.0 / 500.0, 1e-4) <= per_term
    assert variance_false_alarm_rate(design, 12, h - 0.01, 2.0 / 500.0, 1e-4) > per_term
    with pytest.raises(ValueError, match="per-term rate"):
        variance_threshold(design, 12, 1.5)


def test_the_schedule_falls_to_the_known_variance_threshold() -> None:
    design = VarianceDesign()
    per_term = 1.0 / 3600.0 / 75.0
    terms, h = threshold_schedule(design, 48, per_term, 150.0)
    assert terms[0] == 150.0 and np.all(np.diff(terms) > 0) and np.all(np.diff(h) <= 0)
    assert h[-1] == variance_threshold(design, 48, per_term)
    assert h[0] > h[-1] + 5.0  # 150 terms: a variance 11.5 % uncertain costs ~9 in h
    _known_terms, known = threshold_schedule(design, 48, per_term, math.inf)
    assert known.size == 1 and known[0] == h[-1]


def test_lorden_reference() -> None:
    assert variance_information(1.0) == 0.0
    assert variance_information(9.0) == pytest.approx(0.5 * (8.0 - math.log(9.0)))
    assert lorden_variance_terms(9.0, 1e8, 10) == pytest.approx(math.log(1e9) / 2.901, rel=1e-3)
    assert lorden_variance_terms(1.0, 1e8, 10) == math.inf


# --- Helmert contrasts ---------------------------------------------------------------------


def _plain_contrasts(x: np.ndarray, block: int) -> np.ndarray:
    out = np.full_like(x, np.nan)
    for t in range(x.shape[0]):
        j = t % block
        if j:
            out[t] = (x[t] - x[t - j : t].mean(axis=0)) * math.sqrt(j / (j + 1.0))
    return out


def test_helmert_contrasts_follow_the_definition_for_any_split() -> None:
    rng = np.random.default_rng(1)
    x = 3.0 + rng.standard_normal((1001, 4))
    whole = HelmertContrasts(4, 4).push(x)
    np.testing.assert_allclose(whole, _plain_contrasts(x, 4), rtol=0, atol=1e-12)
    stream = HelmertContrasts(4, 4)
    cuts = [0, 1, 3, 10, 11, 500, 1001]
    parts = np.concatenate([stream.push(x[a:b]) for a, b in itertools.pairwise(cuts)])
    np.testing.assert_array_equal(parts, whole)


def test_helmert_contrasts_of_white_noise_are_independent_and_mean_free() -> None:
    rng = np.random.default_rng(2)
    x = rng.standard_normal((200_000, 2))
    terms = HelmertContrasts(2, 4).push(x)
    valid = terms[~np.isnan(terms[:, 0])]
    assert valid.shape[0] == 150_000
    # 150,000 terms: standard errors 0.0026 (mean), 0.0037 (variance), 0.0026 (correlation)
    assert np.all(np.abs(valid.mean(axis=0)) < 0.015)
    assert np.all(np.abs(valid.var(axis=0) - 1.0) < 0.02)
    squares = valid[:, 0] ** 2
    assert abs(np.corrcoef(squares[:-1], squares[1:])[0, 1]) < 0.015
    assert abs(np.corrcoef(valid[:-1, 0], valid[1:, 0])[0, 1]) < 0.015
    # a constant and a step between blocks change nothing
    shifted = x + np.where(np.arange(x.shape[0]) >= 400, 5.0, 1.0)[:, None]
    np.testing.assert_allclose(HelmertContrasts(2, 4).push(shifted), terms, atol=1e-9)


def test_the_winsorizer_bounds_outliers_and_counts_them() -> None:
    rng = np.random.default_rng(3)
    x = rng.standard_normal((20_000, 3))
    x[5000, 1] += 30.0
    x[9000:9005, 2] += 12.0
    bounded = Winsorizer(np.ones(3), 4.0, 10.0, np.zeros(3))
    out = bounded.push(x)
    assert abs(out[5000, 1]) < 5.0 and abs(out[9000, 2]) < 5.0
    assert bounded.outliers[1] >= 1 and bounded.outliers[2] >= 3
    assert np.mean(out == x) > 0.999  # white noise passes unchanged
    assert 0 < bounded.outlier_share() < 1e-3


# --- the bank ------------------------------------------------------------------------------


def _bank(n: int, per_hour: float, **kwargs: float) -> VarianceCusumBank:
    design = VarianceDesign(scale_tau_s=0.0)
    h = variance_threshold(design, n, per_hour / 3600.0 / (0.75 * RATE_HZ))
    return VarianceCusumBank(design, h, np.ones(n, bool), RATE_HZ, **kwargs)


def test_white_noise_keeps_the_bank_within_its_budget() -> None:
    # 2 hours of 16 white columns at 360/h: the union bound allows 720 episodes; the bank
    # raises about 0.75 of it (Poisson sd ~25)
    bank = _bank(16, 360.0)
    contrasts = HelmertContrasts(16, 4)
    rng = np.random.default_rng(4)
    for _ in range(2 * 3600 * 100 // 4000):
        bank.process(contrasts.push(rng.standard_normal((4000, 16))))
    assert 0.5 * 720 < bank.episodes <= 720


def _growth(factor: float, rng: np.random.Generator, n: int = 8) -> np.ndarray:
    x = rng.standard_normal((3000, n))
    x[1000:2000, 5] *= factor  # the noise of sensor 5 grows for 10 s
    return HelmertContrasts(n, 4).push(x)


def test_a_noise_growth_is_detected_isolated_sized_then_released() -> None:
    bank = _bank(8, 1.0)
    out = bank.process(_growth(3.0, np.random.default_rng(1000)))
    alarmed = np.flatnonzero(out.alarm)
    assert not out.alarm[:1000].any()
    assert 1000 <= alarmed[0] < 1000 + 30  # the optimal test needs ~10 terms here
    assert 2000 <= alarmed[-1] < 2000 + 80  # "back to nominal" within ~0.5 s
    during = out.alarm[1000:2000]
    assert during.mean() > 0.97
    assert np.all(out.isolated[out.alarm] == 5)
    assert np.all(out.isolated[~out.alarm] == NO_ISOLATION)
    # the amplitude is the standard deviation ratio since the onset (3, its clip ignored)
    assert np.nanmedian(out.amplitude[1500:2000]) == pytest.approx(3.0, rel=0.1)
    assert out.scores.shape == (3000, 8) and np.all(out.statistic >= 0)
    assert bank.episodes == 1


def test_a_lone_outlier_raises_no_alarm() -> None:
    rng = np.random.default_rng(6)
    x = rng.standard_normal((2000, 4))
    x[1000, 2] = 50.0
    bounded = Winsorizer(np.ones(4), 4.0, 10.0, np.zeros(4))
    out = _bank(4, 1.0).process(HelmertContrasts(4, 4).push(bounded.push(x)))
    assert not out.alarm.any()


def test_the_outputs_do_not_depend_on_how_the_rows_are_split() -> None:
    z = _growth(2.5, np.random.default_rng(7))
    whole = _bank(8, 36.0, calibration_terms=300.0).process(z)
    bank = _bank(8, 36.0, calibration_terms=300.0)
    cuts = [0, 7, 101, 333, 1234, 2048, 2999, 3000]
    parts = [bank.process(z[a:b]) for a, b in itertools.pairwise(cuts)]
    for name in ("statistic", "alarm", "isolated", "threshold"):
        joined = np.concatenate([getattr(p, name) for p in parts])
        np.testing.assert_allclose(joined, getattr(whole, name), rtol=1e-9, atol=1e-9)


def test_not_isolable_sensors_are_reported_as_such() -> None:
    design = VarianceDesign(scale_tau_s=0.0)
    isolable = np.array([True, True, True, True, True, False, True, True])
    bank = VarianceCusumBank(design, 10.0, isolable, RATE_HZ)
    out = bank.process(_growth(3.0, np.random.default_rng(8)))
    assert out.alarm.any() and np.all(out.isolated[out.alarm] == NOT_ISOLABLE)
    assert np.all(np.isnan(out.amplitude[out.alarm]))


def test_the_tracked_variance_learns_a_variance_calibrated_too_small() -> None:
    # the calibration said 1, the noise is 1.15 in variance: without tracking the bank
    # takes it for a growth again and again; the running mean learns it within seconds
    rng = np.random.default_rng(9)
    z = HelmertContrasts(8, 4).push(math.sqrt(1.15) * rng.standard_normal((360_000, 8)))
    design = VarianceDesign(scale_tau_s=600.0)
    h = variance_threshold(design, 8, 36.0 / 3600.0 / 75.0)
    fixed = VarianceCusumBank(VarianceDesign(scale_tau_s=0.0), h, np.ones(8, bool), RATE_HZ)
    tracked = VarianceCusumBank(design, h, np.ones(8, bool), RATE_HZ, calibration_terms=500.0)
    fixed.process(z)
    tracked.process(z)
    assert tracked.variance == pytest.approx(np.full(8, 1.15), rel=0.05)
    assert tracked.episodes < fixed.episodes / 3


def test_a_schedule_lowers_the_threshold_as_the_variance_is_learnt() -> None:
    design = VarianceDesign()
    per_term = 1.0 / 3600.0 / 75.0
    schedule = threshold_schedule(design, 8, per_term, 150.0)
    bank = VarianceCusumBank(design, schedule, np.ones(8, bool), RATE_HZ, calibration_terms=150.0)
    out = bank.process(
        HelmertContrasts(8, 4).push(np.random.default_rng(10).standard_normal((30_000, 8)))
    )
    assert out.threshold[0] == schedule[1][0]
    assert out.threshold[-1] < out.threshold[0]
    assert np.all(np.diff(out.threshold) <= 0)
    assert out.threshold[-1] == pytest.approx(schedule[1][-1], abs=0.5)


def test_nan_terms_count_as_none_and_shapes_are_checked() -> None:
    bank = _bank(3, 1.0)
    out = bank.process(np.full((50, 3), np.nan))
    assert not out.alarm.any() and np.all(out.statistic == 0.0)
    with pytest.raises(ValueError, match="evidence"):
        bank.process(np.zeros((5, 4)))
