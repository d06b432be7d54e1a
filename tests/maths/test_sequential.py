"""maths.sequential: the robust CUSUM bank, its run lengths, thresholds and decisions."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from imufdi_cli.maths.sequential import (
    NO_ISOLATION,
    NOT_ISOLABLE,
    CusumBank,
    CusumDesign,
    average_run_length,
    budget_threshold,
    false_alarm_rate,
    increments,
    long_run_factor,
    lorden_delay_samples,
    lorden_drift_samples,
    outlier_share,
    outlier_size,
    spatial_inflation,
    step_information,
)

RATE_HZ = 100.0


def test_run_length_matches_the_published_cusum_tables() -> None:
    # A huge clip and shift 1 make (1)-(2) the classic CUSUM of reference value k = 0.5: the
    # one-sided ARL at h = 4 and 5 is twice the two-sided 168 and 465 of Montgomery's Table
    # 9.3 (Brook & Evans' Markov chain with enough states converges to 335.4 and 930.9;
    # the tables round to 3 figures: 0.5 %).
    assert average_run_length(1.0, 50.0, 4.0) == pytest.approx(2 * 168, rel=5e-3)
    assert average_run_length(1.0, 50.0, 5.0) == pytest.approx(2 * 465, rel=5e-3)


def test_run_length_of_the_clipped_increments_matches_a_simulation() -> None:
    # 4000 CUSUMs side by side for 3000 steps: ~2,300 alarms at ARL ~5,000, so the simulated
    # ARL has a relative standard error of ~2 %; 4 standard errors
    rng = np.random.default_rng(20251201)
    shift, clip, h = 3.0, 3.5, 9.0
    columns, steps = 4000, 3000
    statistic = np.zeros(columns)
    alarms = 0
    for _ in range(steps):
        statistic = np.maximum(
            0.0, statistic + increments(shift, clip, rng.standard_normal(columns))
        )
        hit = statistic >= h
        alarms += int(np.count_nonzero(hit))
        statistic[hit] = 0.0
    simulated = columns * steps / alarms
    assert average_run_length(shift, clip, h) == pytest.approx(simulated, rel=4 / math.sqrt(alarms))


def test_outliers_and_sigma_errors_shorten_the_run_length() -> None:
    clean = average_run_length(1.0, 3.5, 12.0)
    assert average_run_length(1.0, 3.5, 12.0, contamination=1e-3) < clean
    assert (
        average_run_length(1.0, 3.5, 12.0, scale=1.05)
        < clean
        < average_run_length(1.0, 3.5, 12.0, scale=0.95)
    )
    design = CusumDesign()
    base = false_alarm_rate(design, 48, 14.0)
    assert false_alarm_rate(design, 48, 14.0, scale_variance=0.01) > base
    assert false_alarm_rate(design, 48, 14.0, contamination=1e-3) > base


@pytest.mark.parametrize("budget_per_hour", [0.1, 1.0, 3600.0])
def test_budget_threshold_meets_the_rate_asked(budget_per_hour: float) -> None:
    design = CusumDesign()
    per_sample = budget_per_hour / 3600.0 / RATE_HZ
    h = budget_threshold(design, 48, per_sample)
    # at h the bound is at or just below the budget (h is rounded up to 1e-3), and 0.01
    # lower it is above
    assert false_alarm_rate(design, 48, h) <= per_sample
    assert false_alarm_rate(design, 48, h) > 0.98 * per_sample
    assert false_alarm_rate(design, 48, h - 0.01) > per_sample


def test_budget_threshold_refuses_an_impossible_rate() -> None:
    with pytest.raises(ValueError, match="per-sample rate"):
        budget_threshold(CusumDesign(), 8, 1.0)


def test_lorden_references() -> None:
    # 2 ln(gamma K) / delta^2 for a step; the ramp's m from slope^2 m^3 / 3 = 2 ln(gamma K)
    assert lorden_delay_samples(4.0, 1e6, 10) == pytest.approx(2 * math.log(1e7) / 4.0)
    m = lorden_drift_samples(0.1, 1e6, 10)
    assert 0.01 * m**3 / 3 == pytest.approx(2 * math.log(1e7))
    assert lorden_delay_samples(0.0, 1e6, 10) == math.inf


def test_long_run_factor_of_white_and_correlated_noise() -> None:
    rng = np.random.default_rng(7)
    white = rng.standard_normal((20000, 8))
    assert long_run_factor(white, 20) == pytest.approx(1.0, abs=0.06)
    # AR(1) with phi = 0.5: the long-run variance factor (1 + phi) / (1 - phi) = 3, less
    # the finite-block bias 2 phi (1 - phi^L) / (L (1 - phi)^2) = 0.2 at L = 20
    ar = np.zeros_like(white)
    for t in range(1, white.shape[0]):
        ar[t] = 0.5 * ar[t - 1] + white[t]
    assert long_run_factor(ar / ar.std(axis=0), 20) == pytest.approx(2.8, rel=0.08)


def test_outlier_share_counts_what_a_gaussian_does_not_explain() -> None:
    rng = np.random.default_rng(8)
    z = rng.standard_normal((50000, 4))
    assert outlier_share(z) < 1e-4
    z[rng.random(z.shape) < 0.002] = 7.0
    assert outlier_share(z) == pytest.approx(0.002, rel=0.15)


def test_outlier_size_is_the_median_magnitude_beyond_the_level() -> None:
    z = np.zeros(100)
    z[:3] = (6.0, -7.0, 9.0)
    assert outlier_size(z) == 7.0
    assert outlier_size(np.zeros(10)) == 0.0


def _mixture_information(delta: float, p: float, o: float) -> float:
    # an independent route: scipy's adaptive quadrature of f1 ln(f1 / f0) in log space,
    # breakpoints at the components' centres, over f1's mass (12 sd beyond its outliers)
    from scipy import integrate, special, stats

    def log_f0(x: float) -> float:
        terms = [stats.norm.logpdf(x), stats.norm.logpdf(x - o), stats.norm.logpdf(x + o)]
        return float(special.logsumexp(terms, b=[1 - p, p / 2, p / 2]))

    def integrand(y: float) -> float:
        log_f1 = log_f0(y - delta)
        return math.exp(log_f1) * (log_f1 - log_f0(y))

    points = sorted({0.0, delta, o, -o, o + delta, delta - o})
    lo, hi = delta - o - 12.0, delta + o + 12.0
    value, _ = integrate.quad(integrand, lo, hi, points=points, limit=500)
    return value


@pytest.mark.parametrize("delta", [0.5, 1.94, 3.0, 5.81, 6.45, 8.0, 12.0])
def test_step_information_in_noise_with_outliers(delta: float) -> None:
    # Gaussian evidence: delta^2 / 2 exactly
    assert step_information(delta**2) == pytest.approx(delta**2 / 2, rel=1e-15)
    assert step_information(delta**2, 0.001, 0.0) == pytest.approx(delta**2 / 2, rel=1e-15)
    # paper-table4's gyros: 0.1 % outliers of 6.45 standard deviations of the evidence.
    # 1e-5: the 96-node Gauss-Hermite rule and the adaptive quadrature agree to within
    # 6e-7 over this grid (the integrand's transitions are on the noise's own scale)
    got = float(step_information(delta**2, 0.001, 6.45))
    assert got == pytest.approx(_mixture_information(delta, 0.001, 6.45), rel=1e-5)
    assert got <= delta**2 / 2  # data processing: outliers added to both laws


def test_a_step_the_size_of_the_outliers_carries_half_the_gaussian_information() -> None:
    # 0.9 deg/s on paper-table4 (delta 5.81) against outliers of 1 deg/s (6.45): each
    # sample carries about ln(phi(0) / (p/2 phi(delta - o))) = 7.8 nats, not 16.9
    information = float(step_information(5.81**2, 0.001, 6.45))
    assert 7.0 < information < 7.9
    gaussian = lorden_delay_samples(5.81**2, 360000.0, 96)
    assert lorden_delay_samples(5.81**2, 360000.0, 96, 0.001, 6.45) == pytest.approx(
        gaussian * 5.81**2 / 2 / information, rel=1e-12
    )


def test_the_drift_reference_accumulates_the_information() -> None:
    target = math.log(1e7)
    gaussian = lorden_drift_samples(0.1, 1e6, 10)
    m = lorden_drift_samples(0.1, 1e6, 10, 0.002, 5.0)
    assert m > gaussian
    # the information accumulated over the ramp's first m samples (trapezoids, 20001
    # points: their error is far below the 1e-6 asked) reaches ln(gamma K)
    t = np.linspace(0.0, m, 20001)
    info = step_information((0.1 * t) ** 2, 0.002, 5.0)
    assert float(np.sum((info[1:] + info[:-1]) / 2 * np.diff(t))) == pytest.approx(target, rel=1e-6)


def _bank(n: int = 8, budget_per_hour: float = 1.0, **design: float) -> CusumBank:
    cusum = CusumDesign(**design)  # type: ignore[arg-type]
    h = budget_threshold(cusum, n, budget_per_hour / 3600.0 / RATE_HZ)
    return CusumBank(cusum, h, np.ones(n), np.ones(n, bool), RATE_HZ)


def test_white_noise_keeps_the_bank_within_its_budget() -> None:
    # 2 hours of 16 white channels at a budget of 360/h: the union bound allows 720
    # episodes at the worst motion scale (the design grid's effective shifts mu / s are
    # most alarm-prone for s near 16-32, about 3x s = 1); at rest the bank raises about
    # a third of it, at a motion scale of 16 about 0.9 (Poisson sd 15-25)
    rng = np.random.default_rng(9)
    rest, moving = _bank(16, 360.0), _bank(16, 360.0)
    scale2 = np.full(4000, 16.0**2)
    for _ in range(2 * 3600 * 100 // 4000):
        rest.process(rng.standard_normal((4000, 16)))
        moving.process(16.0 * rng.standard_normal((4000, 16)), factors=scale2)
    assert 0.15 * 720 < rest.episodes < 0.6 * 720
    assert 0.5 * 720 < moving.episodes <= 720


def test_a_step_is_detected_isolated_and_sized_then_released() -> None:
    rng = np.random.default_rng(10)
    bank = _bank(8)
    z = rng.standard_normal((3000, 8))
    z[1000:2000, 5] += 2.0  # a step of 2 standard deviations on sensor 5, for 10 s
    out = bank.process(z)
    alarms = np.flatnonzero(out.alarm)
    assert bank.episodes == 1
    # optimal (Lorden) ~ 2 ln(gamma K) / 4 = 10 samples; the bank within 2x of it
    assert 1000 <= alarms[0] <= 1000 + 2 * lorden_delay_samples(4.0, 3600 * 100, 32)
    assert set(out.isolated[alarms].tolist()) == {5}
    assert np.nanmedian(out.amplitude[alarms]) == pytest.approx(2.0, rel=0.05)
    # released within a few tens of samples of the end, and quiet afterwards
    assert 2000 <= alarms[-1] < 2000 + 60
    assert not out.alarm[alarms[-1] + 1 :].any()
    assert (out.isolated[~out.alarm] == NO_ISOLATION).all()


def test_a_lone_outlier_raises_no_alarm() -> None:
    bank = _bank(8)
    z = np.zeros((200, 8))
    z[100, 3] = 50.0  # one absurd sample: clipped to 3.5
    assert not bank.process(z).alarm.any()


def test_not_isolable_sensors_are_reported_as_such() -> None:
    cusum = CusumDesign()
    h = budget_threshold(cusum, 4, 1 / 3600 / RATE_HZ)
    isolable = np.array([True, True, False, False])
    bank = CusumBank(cusum, h, np.ones(4), isolable, RATE_HZ)
    z = np.zeros((300, 4))
    z[100:, 2] = 3.0
    out = bank.process(z)
    assert out.alarm.any()
    assert set(out.isolated[out.alarm].tolist()) == {NOT_ISOLABLE}
    assert np.isnan(out.amplitude[out.alarm]).all()


@pytest.mark.parametrize(
    "cuts",
    [
        [1, 777, 3001],
        # calls that start inside an episode after its hold, and just before and after its
        # end: the references learn every row once, whatever the calls' bounds
        [1500, 2999, 4100, 4170, 5000, 6020, 6100, 6200, 8000],
        list(range(333, 9000, 333)),
    ],
)
def test_the_outputs_do_not_depend_on_how_the_rows_are_split(cuts: list[int]) -> None:
    rng = np.random.default_rng(11)
    z = rng.standard_normal((9000, 6)) * 1.1
    z[2000:4000, 2] -= 1.5  # longer than the 10 s hold: the references learn again in it
    z[6000:6050, 4] += 4.0
    whole = _bank(6, 50.0).process(z)
    pieces = _bank(6, 50.0)
    bounds = [0, *cuts, 9000]
    parts = [pieces.process(z[a:b]) for a, b in itertools.pairwise(bounds)]
    assert whole.alarm[2000:4000].mean() > 0.9 and whole.alarm[6000:6050].any()
    for name in ("alarm", "isolated"):
        assert np.array_equal(
            getattr(whole, name), np.concatenate([getattr(p, name) for p in parts])
        )
    for name in ("statistic", "amplitude"):
        # the cumulative sums restart at each call: rounding of sums of ~1e4 terms of O(1)
        joined = np.concatenate([getattr(p, name) for p in parts])
        np.testing.assert_allclose(getattr(whole, name), joined, rtol=1e-9, atol=1e-9)


def test_the_reference_follows_slow_wander_but_not_a_detected_fault() -> None:
    rng = np.random.default_rng(12)
    minutes = 20
    n_rows = minutes * 60 * 100
    # 1.2 sd of wander over 20 minutes: at tau = 20 s the reference lags it by at most
    # 1.2 x 2 pi / 1200 s x 20 s = 0.13 sd (a CUSUM of shift mu is exponentially sensitive
    # to an offset e: its run length scales like exp(-2 e h / mu))
    wander = 1.2 * np.sin(np.linspace(0, 2 * np.pi, n_rows))[:, None]
    z = rng.standard_normal((n_rows, 4)) + wander * np.array([1.0, -1.0, 0.5, 0.0])
    tracked = _bank(4, 1.0, tau_s=20.0)
    untracked = _bank(4, 1.0, tau_s=0.0)
    for start in range(0, n_rows, 4096):
        tracked.process(z[start : start + 4096])
        untracked.process(z[start : start + 4096])
    # tracked: what white noise alone gives at 1/h over 20 min of 4 sensors (0-3);
    # untracked: the wander alone raises tens of episodes
    assert tracked.episodes <= 2 and untracked.episodes > 20
    # a fault after the wander: detected, and the reference frozen while it lasts
    fault = rng.standard_normal((3000, 4))
    fault[500:, 1] += 3.0
    before = tracked.reference.copy()
    out = tracked.process(fault)
    assert out.alarm[600:].all()
    np.testing.assert_array_equal(tracked.reference, _frozen_value(tracked, before))


def _frozen_value(bank: CusumBank, before: np.ndarray) -> np.ndarray:
    """The reference once an episode is open: what it was at the alarm (it may have moved
    over the ~5 s before it, never by more than 5 s / 20 s of the gate's +-3)."""
    assert bank.episode is not None
    assert np.all(np.abs(bank.reference - before) <= 3.0 * 5.0 / 20.0 + 1e-12)
    return bank.reference


def test_nan_evidence_counts_as_none_and_shapes_are_checked() -> None:
    bank = _bank(3)
    z = np.full((50, 3), np.nan)
    out = bank.process(z)
    assert not out.alarm.any() and (out.statistic == 0).all()
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        bank.process(np.zeros((5, 4)))


def test_the_motion_model_learns_a_residual_proportional_to_the_state() -> None:
    # a residual scale error: column 2's evidence carries 1.5 sd per unit of a swinging
    # state (a rate), which a CUSUM of shift 2 alarms on in half swings
    from imufdi_cli.maths.sequential import MotionModel

    rng = np.random.default_rng(13)
    n_rows = 60 * 100 * 5
    t = np.arange(n_rows) / RATE_HZ
    state = np.stack([np.sin(2 * np.pi * 0.3 * t), np.cos(2 * np.pi * 0.2 * t), 0.0 * t], axis=1)
    z = rng.standard_normal((n_rows, 4))
    z[:, 2] += 1.5 * state[:, 0]
    cusum = CusumDesign()
    h = budget_threshold(cusum, 4, 1 / 3600 / RATE_HZ)

    def run(motion: MotionModel | None) -> list[float]:
        """Seconds at which episodes start."""
        bank = CusumBank(cusum, h, np.ones(4), np.ones(4, bool), RATE_HZ, motion=motion)
        starts: list[float] = []
        for start in range(0, n_rows, 4096):
            out = bank.process(z[start : start + 4096], state[start : start + 4096])
            rising = out.alarm & ~np.concatenate([[False], out.alarm[:-1]])
            starts += [(start + int(i)) / RATE_HZ for i in np.flatnonzero(rising)]
        return starts

    calibration = slice(0, 200)  # 2 s: a sixth of a swing
    model = MotionModel.from_calibration(state[calibration], z[calibration], 1.0, 600 * RATE_HZ)
    learnt = run(model)
    # while it learns (the first half minute) a few episodes at most, then none
    assert len(learnt) <= 3 and all(t < 30.0 for t in learnt)
    assert len(run(None)) > 20


def test_a_tracked_variance_corrects_a_sigma_calibrated_too_small() -> None:
    rng = np.random.default_rng(14)
    z = rng.standard_normal((30 * 60 * 100, 8)) * 1.15  # sigma 15 % too small
    fixed, tracked = _bank(8, 10.0, scale_tau_s=0.0), _bank(8, 10.0)
    for start in range(0, z.shape[0], 4096):
        fixed.process(z[start : start + 4096])
        tracked.process(z[start : start + 4096])
    # at 10/h for 30 min: ~5 allowed; 1.15 sd multiplies the rate by ~exp(h (1 - 1/1.15^2))
    assert tracked.episodes <= 8 < fixed.episodes
    np.testing.assert_allclose(tracked.ref.variance, 1.15**2, rtol=0.05)


def test_a_step_in_motion_is_caught_by_a_design_of_its_physical_size() -> None:
    # in motion the noise is 8 times its rest level: a step of 16 rest sd is 2 sd of the
    # moving noise, the effective shift of the design 16; the rest designs 2 and 4 (an
    # effective 0.25 and 0.5) would need hundreds of samples
    rng = np.random.default_rng(15)
    bank = _bank(6)
    scale = 8.0
    z = scale * rng.standard_normal((4000, 6))
    z[2000:, 4] += 16.0
    out = bank.process(z, factors=np.full(4000, scale**2))
    first = int(np.flatnonzero(out.alarm)[0])
    assert 2000 <= first <= 2000 + 2 * lorden_delay_samples(4.0, 3600 * 100, 12)
    assert (out.isolated[out.alarm] == 4).mean() > 0.99
    assert np.nanmedian(out.amplitude[out.alarm]) == pytest.approx(16.0, rel=0.1)


def _spatial_ville(columns: int, c: float, order: bool = True) -> float:
    # an independent route to the largest E[exp(a clip(r e) - a^2/2)] over the shifts:
    # Monte Carlo over the rows' spread (300 000 rows; the order statistic ceil(n/2) that
    # spatial_inflation takes, or numpy's median, the mean of the two middle ones for an
    # even n) and scipy's normal law for e
    from scipy import stats

    rng = np.random.default_rng(21)
    squares = rng.standard_normal((300_000, columns)) ** 2
    if order:
        middle = np.partition(squares, (columns + 1) // 2 - 1, axis=1)[:, (columns + 1) // 2 - 1]
    else:
        middle = np.median(squares, axis=1)
    m = middle / 0.4549364231195724
    r = 1.0 / np.sqrt(c * m)
    worst = 0.0
    for a in np.geomspace(0.25, 7.0, 25):  # (rows whose closed form overflows carry ~0)
        edge = 3.5 / r
        with np.errstate(over="ignore", invalid="ignore"):
            inside = np.exp(0.5 * a * a * (r * r - 1.0)) * (
                stats.norm.cdf(edge - a * r) - stats.norm.cdf(-edge - a * r)
            )
        beyond = (np.exp(3.5 * a) + np.exp(-3.5 * a)) * np.exp(-0.5 * a * a) * stats.norm.sf(edge)
        worst = max(worst, float(np.mean(np.where(np.isfinite(inside), inside, 0.0) + beyond)))
    return worst


@pytest.mark.parametrize(("columns", "want"), [(12, 2.689), (24, 1.546), (96, 1.084)])
def test_spatial_inflation_is_where_the_increments_exponential_moment_reaches_one(
    columns: int, want: float
) -> None:
    c = spatial_inflation(columns)
    assert c == pytest.approx(want, abs=2e-3)
    # Ville's condition holds at c and fails 5 % below it (the Monte Carlo's sd is about
    # 0.2 % of the moment: well inside the 5 % step, whose moment moves by 2-4 %)
    assert _spatial_ville(columns, c) < 1.005
    assert _spatial_ville(columns, 0.95 * c) > 1.005
    # the bank's median (for an even n the mean of the two middle squares) is larger than
    # the lower one: the margin errs on the safe side
    assert _spatial_ville(columns, c, order=False) < 1.0
    assert spatial_inflation(48) < spatial_inflation(24) < spatial_inflation(12)


def _scale_mixture(rng: np.random.Generator, rows: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    # a motion residual as the MIMU4444 accelerometers show it: white in time, its size
    # changing from row to row alike on every sensor (log-normal, median 30 rest sd)
    scale = 30.0 * np.exp(rng.standard_normal(rows))
    return scale[:, None] * rng.standard_normal((rows, n)), scale


def test_the_spatial_variance_holds_the_budget_on_a_row_scaled_motion_residual() -> None:
    # 1 hour of 24 channels in motion at 360/h: a jitter-style factor that covers the
    # largest rows (60 x the median variance) raises almost nothing, and the rows' own
    # spatial variance also stays within the budget's union bound of 360
    rng = np.random.default_rng(22)
    cusum = CusumDesign()
    h = budget_threshold(cusum, 24, 360.0 / 3600.0 / RATE_HZ / 2.0, 0.0, cusum.motion_outliers)
    spatial = CusumBank(cusum, h, np.ones(24), np.ones(24, bool), RATE_HZ, spatial=True)
    for _ in range(3600 * 100 // 4000):
        z, _ = _scale_mixture(rng, 4000, 24)
        spatial.process(z, factors=np.full(4000, 60.0 * 900.0))
    assert spatial.episodes <= 360


def test_the_spatial_variance_finds_a_step_the_jitter_margin_hides() -> None:
    rng = np.random.default_rng(23)
    cusum = CusumDesign()
    h = budget_threshold(cusum, 24, 1.0 / 3600.0 / RATE_HZ / 2.0, 0.0, cusum.motion_outliers)
    z, _ = _scale_mixture(rng, 3000, 24)
    z[1000:, 7] += 45.0  # 1.5 times the motion residual's median size
    factors = np.full(3000, 60.0 * 900.0)
    found = {}
    for spatial in (False, True):
        bank = CusumBank(cusum, h, np.ones(24), np.ones(24, bool), RATE_HZ, spatial=spatial)
        out = bank.process(z, factors=factors)
        alarms = np.flatnonzero(out.alarm)
        found[spatial] = int(alarms[0]) - 1000 if alarms.size else None
        if alarms.size:
            assert alarms[0] >= 1000 and (out.isolated[alarms] == 7).mean() > 0.95
    assert found[True] is not None and found[True] < 100
    assert found[False] is None or found[False] > 4 * found[True]


def test_the_spatial_variance_is_a_function_of_each_row() -> None:
    # the same decisions however the rows are split into calls, and rows at rest (factor
    # at most rest_factor) keep their factor: at rest the bank is the one without it
    rng = np.random.default_rng(24)
    cusum = CusumDesign()
    h = budget_threshold(cusum, 24, 50.0 / 3600.0 / RATE_HZ)
    z, _ = _scale_mixture(rng, 6000, 24)
    z[:2000] /= 30.0 * np.exp(rng.standard_normal((2000, 1)))  # back to unit noise at rest
    z[3000:3400, 3] += 60.0
    factors = np.r_[np.ones(2000), np.full(4000, 5e4)]

    def bank(spatial: bool) -> CusumBank:
        return CusumBank(cusum, h, np.ones(24), np.ones(24, bool), RATE_HZ, spatial=spatial)

    whole = bank(True).process(z, factors=factors)
    pieces = bank(True)
    bounds = [0, 1, 1999, 2001, 3100, 4500, 6000]
    parts = [pieces.process(z[a:b], factors=factors[a:b]) for a, b in itertools.pairwise(bounds)]
    assert whole.alarm[3000:3400].any()
    assert np.array_equal(whole.alarm, np.concatenate([p.alarm for p in parts]))
    # cumulative sums restart at each call: rounding of sums of ~1e3 terms
    np.testing.assert_allclose(
        whole.statistic, np.concatenate([p.statistic for p in parts]), rtol=1e-9, atol=1e-9
    )
    rest = bank(False).process(z[:2000], factors=factors[:2000])
    np.testing.assert_array_equal(rest.statistic, whole.statistic[:2000])


def test_the_references_learn_at_rest_only_and_resume_after_a_hold() -> None:
    bank = _bank(4, 1.0, tau_s=20.0)
    rng = np.random.default_rng(16)
    # motion rows (variance factor 9) with an offset of 0.2 rest sd (too small to alarm
    # there; at rest the running mean would take it whole): the reference does not move
    moving = bank.process(3.0 * rng.standard_normal((3000, 4)) + 0.2, factors=np.full(3000, 9.0))
    assert not moving.alarm.any()
    assert np.all(np.abs(bank.reference) < 0.05)
    # at rest, a bias jump of 2.5 sd on sensor 1 that lasts (as a wander step would):
    # detected, the reference frozen for hold_s (10 s), then it absorbs the jump and the
    # episode ends instead of latching. The innovation gate (a 1 s sub-block's sum clipped
    # at 3 sqrt(100) = 30 sd, at gain 1 / (20 s x 100 Hz)) lets the reference move at most
    # 0.015 sd/s: 2.5 sd take about two minutes after the holds
    z = rng.standard_normal((180 * 100, 4))
    z[1000:, 1] += 2.5
    out = bank.process(z)
    alarms = np.flatnonzero(out.alarm)
    assert 1000 <= alarms[0] < 1100
    assert alarms[-1] - alarms[0] > 10 * 100  # at least the hold
    assert not out.alarm[-40 * 100 :].any()  # then learnt: quiet for the last 40 s
    assert bank.reference[1] == pytest.approx(2.5, abs=0.3)


def test_a_latched_episode_keeps_the_references_until_the_fault_ends() -> None:
    # the same lasting jump with hold_s = inf (glt.hold=latch): one episode while it lasts,
    # the reference never learns it, and the episode ends when the jump goes away
    rng = np.random.default_rng(16)
    bank = _bank(4, 1.0, tau_s=20.0, hold_s=math.inf)
    bank.process(rng.standard_normal((1000, 4)))
    before = bank.reference.copy()
    z = rng.standard_normal((180 * 100, 4))
    z[1000:15000, 1] += 2.5
    out = bank.process(z)
    alarms = np.flatnonzero(out.alarm)
    assert 1000 <= alarms[0] < 1100 and bank.episodes == 1
    assert out.alarm[1100:15000].all()  # no sample of the fault is missed once detected
    assert 15000 <= alarms[-1] < 15100 and not out.alarm[15100:].any()
    # frozen through the episode: what it learnt is what 0.2 s of rest before the alarm
    # and the rest after the end taught it (at most 3 sub-block gates of 3 sd / 20 s)
    assert abs(bank.reference[1] - before[1]) < 0.5


def test_a_fault_beyond_the_clip_stays_one_episode() -> None:
    # a step of 10 sd: the clipped increments of a "fault has ended" test sized at the
    # unclipped mean (10) would be negative while the fault lasts, and release it at once
    rng = np.random.default_rng(17)
    bank = _bank(8)
    z = rng.standard_normal((3000, 8))
    z[1000:2000, 5] += 10.0
    out = bank.process(z)
    assert bank.episodes == 1
    assert out.alarm[1010:2000].all() and not out.alarm[2010:].any()
    assert set(out.isolated[out.alarm].tolist()) == {5}
    assert np.nanmedian(out.amplitude[out.alarm]) == pytest.approx(10.0, rel=0.05)


def test_the_amplitude_is_at_the_evidence_scale_when_the_variance_is_tracked() -> None:
    # sigma calibrated 15 % too small: the tracked variance (1.32) standardizes z' but a
    # step of 3 z units must still read 3 (the amplitude back at the evidence's scale)
    rng = np.random.default_rng(18)
    bank = _bank(8, 1.0)
    for _ in range(10):
        bank.process(1.15 * rng.standard_normal((6000, 8)))
    assert bank.ref.variance.mean() == pytest.approx(1.15**2, rel=0.05)
    z = 1.15 * rng.standard_normal((3000, 8))
    z[1000:, 2] += 3.0
    out = bank.process(z)
    assert np.nanmedian(out.amplitude[out.alarm]) == pytest.approx(3.0, rel=0.05)


def test_the_sub_chunked_spans_give_the_one_pass_decisions() -> None:
    # the bank walks each span in sub-chunks with its sums carried and stops at the
    # sub-chunk of an alarm or of an episode's end: every output equals one pass per
    # span (sub-chunks as long as the span), through alarms, many short episodes that
    # end inside sub-chunks (bursts of 25 rows), a fault far beyond the clip (one episode:
    # the end test's size is at most c s_t), holds and references that resume
    rng = np.random.default_rng(21)
    z = rng.standard_normal((12_000, 6))
    z[1_500:2_000, 2] += 2.5
    z[4_000:7_000, 4] += 12.0  # a step far beyond the clip
    for start in range(2_200, 3_900, 50):
        z[start : start + 25, 3] += 6.0  # bursts: an episode each
    z[7_000:, 1] += np.linspace(0.0, 10.0, 5_000)
    factors = np.ones(12_000)
    factors[9_000:9_600] = 4.0  # motion: the larger designs come into range
    outputs = []
    for first, sub in ((2048, 2048), (8, 512), (1, 3)):
        bank = _bank(6, 5.0, tau_s=20.0)
        bank.FIRST_ROWS, bank.SUB_ROWS = first, sub
        outputs.append(
            [
                bank.process(z[a:b], factors=factors[a:b])
                for a, b in ((0, 4096), (4096, 9000), (9000, 12_000))
            ]
        )
        assert bank.episodes > 20
    for name in ("statistic", "threshold", "alarm", "isolated", "amplitude", "scores"):
        whole = [np.concatenate([getattr(p, name) for p in run]) for run in outputs]
        np.testing.assert_array_equal(whole[0], whole[1])
        np.testing.assert_array_equal(whole[0], whole[2])


def test_sub_chunks_taken_together_give_the_decisions_of_one_at_a_time() -> None:
    # away from alarms the bank takes consecutive sub-chunks that run the same designs in
    # one pass; against the walk one sub-chunk at a time every output is equal, through
    # motion that takes designs in and out of range on single rows (the smallest design's
    # effective shift below min_shift at a factor of 100, the largest at or above 2 c at
    # rest), statistics held by a design that has gone out of range, alarms and episodes
    rng = np.random.default_rng(23)
    n_rows = 16_000
    factors = np.exp(rng.uniform(0.0, np.log(120.0), n_rows)) * (rng.random(n_rows) < 0.01)
    factors = np.maximum(factors, 1.0)  # rest, with a motion spike on 1 % of the rows
    factors[3_000:4_000] = 16.0  # motion: designs 16 and 32 in range ...
    factors[4_000:6_000] = 1.0  # ... and out of range again, from a statistic held
    factors[9_000:9_500] = 100.0
    z = rng.standard_normal((n_rows, 6)) * np.sqrt(factors)[:, None]
    z[3_500:4_100, 1] += 30.0  # a fault in motion, lasting into the rest after it
    z[7_000:7_400, 4] -= 2.5
    z[12_000:, 2] += np.linspace(0.0, 6.0, 4_000)
    # the call from row 10_000 ends its second sub-chunk with evidence on sensor 3 at rest,
    # then violent motion: the designs 2 to 16 out of range (effective shifts below
    # min_shift), the smaller ones running on from their statistics
    z[10_023, 3] = 3.0
    factors[10_024:10_200] = 1e4
    z[10_024:10_200] *= 100.0
    grouped, plain = _bank(6, 5.0, tau_s=20.0), _bank(6, 5.0, tau_s=20.0)
    plain._groups = lambda walk, feed, n: ((lo, hi, None) for lo, hi in plain._chunks(n))  # type: ignore[method-assign]
    taken = []
    groups = grouped._groups

    def counted(walk, feed, n):  # type: ignore[no-untyped-def]
        for lo, hi, ran in groups(walk, feed, n):
            taken.append(hi - lo)
            yield lo, hi, ran

    grouped._groups = counted  # type: ignore[method-assign]
    bounds = [0, 1_000, 3_333, 3_334, 5_000, 8_192, 10_000, 12_500, n_rows]
    runs = [
        [bank.process(z[a:b], factors=factors[a:b]) for a, b in itertools.pairwise(bounds)]
        for bank in (grouped, plain)
    ]
    assert grouped.episodes == plain.episodes >= 3
    assert 8 + 16 + 32 + 64 + 128 + 256 in taken  # a span's short sub-chunks together
    for name in ("statistic", "threshold", "alarm", "isolated", "amplitude", "scores"):
        whole = [np.concatenate([getattr(p, name) for p in run]) for run in runs]
        np.testing.assert_array_equal(whole[0], whole[1])


def test_run_lengths_solved_together_are_those_of_one_chain_at_a_time(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from imufdi_cli.maths.sequential import thresholds

    keys = [
        (shift, 3.5, h, 100, scale, contamination)
        for shift in (0.354, 2.0, 5.66, 8.0)  # 8: no positive increment (ARL inf)
        for h in (0.0, 4.0, 19.1)  # 0: ARL 1
        for scale in (0.9, 1.05)
        for contamination in (0.0, 1e-4)
    ]
    monkeypatch.setattr(thresholds, "_RUN_LENGTHS", type(thresholds._RUN_LENGTHS)())
    together = thresholds.run_lengths(keys)
    alone = []
    for key in keys:
        thresholds._RUN_LENGTHS.clear()
        alone.append(thresholds.average_run_length(*key))
    assert together == alone  # the same floats
    assert math.inf in together and 1.0 in together
    # a cache smaller than one call's keys: every one returned, the last used kept
    thresholds._RUN_LENGTHS.clear()
    monkeypatch.setattr(thresholds, "_CACHED", 3)
    assert thresholds.run_lengths(keys[:8]) == alone[:8]
    assert thresholds.run_lengths(keys[:2] + keys[20:21]) == [*alone[:2], alone[20]]
    assert list(thresholds._RUN_LENGTHS) == [*keys[:2], keys[20]]


def test_the_spatial_variance_leaves_out_sensors_without_evidence() -> None:
    # a row in motion with a third of its sensors missing (NaN): its spread is the median
    # over the other 16 with their own margin, not dragged down by zeros; a row with
    # fewer than 12 keeps the jitter factor; rows at rest keep theirs
    from imufdi_cli.maths.sequential import spatial_variance

    z = np.full((3, 24), 30.0)
    z[1, :8] = np.nan
    z[2, :14] = np.nan
    v = spatial_variance(z, np.full(3, 50.0), np.ones(24, bool), 3.5, 2.0)
    assert v[0] == pytest.approx(spatial_inflation(24) * 900.0 / 0.4549364231195724)
    assert v[1] == pytest.approx(spatial_inflation(16) * 900.0 / 0.4549364231195724)
    assert v[2] == 50.0
    assert spatial_variance(z, np.ones(3), np.ones(24, bool), 3.5, 2.0).tolist() == [1.0] * 3
