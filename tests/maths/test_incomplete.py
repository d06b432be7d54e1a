"""imufdi_cli.maths.incomplete: the incomplete gamma and beta functions and their inverses.

Oracles: ``scipy.special`` (gammainc, gammaincc, betainc, betaincc and their inverses,
compiled Cephes/Boost code, independent of ours) and closed forms.

Tolerances:
- the log-tails, ``1e-12 max(1, |log tail|)`` absolute on the logarithm (i.e. relative on
  the probability): the series and fractions stop at a relative change below 2^-53; the
  prefactor's logarithm is a sum of terms of order one (Stirling's series from shape 10)
  and of ``a log x``, each rounded once, so a few hundred ulps of the largest term at
  most with the shapes up to 10^4 used here;
- the inverses, ``rtol = 2e-13`` on the quantile against scipy: the Newton iteration
  stops below a relative change of 8 ulps, and the log-tail's error above (amplified by
  ``1 / |d log tail / d log x|``, at most about 1 on these grids) dominates; scipy's own
  inverses carry errors of the same order;
- shapes of 10^4 to 10^6, ``rtol = 1e-10``: there scipy's inverses (not ours) lose
  digits (scipy's gammaincinv(1e6, 1e-12) is 8e-8 off in probability; see the test).
"""

from __future__ import annotations

import math
import sys

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from imufdi_cli.maths import incomplete, quantiles

special = pytest.importorskip("scipy.special")

SHAPES = [0.05, 0.3, 0.5, 1.0, 1.7, 2.0, 5.0, 9.99, 10.0, 12.25, 47.0, 500.0, 1e3, 1e4]
LEVELS = [1e-300, 1e-100, 1e-12, 1e-5, 1e-3, 0.05, 0.3, 0.5, 0.7, 0.95, 0.999, 1 - 1e-9]


def _relative(a: float, b: float) -> float:
    return abs(a - b) / abs(b) if b != 0 else abs(a)


def test_gamma_log_tails_agree_with_scipy() -> None:
    worst = 0.0
    for a in SHAPES:
        for x in [1e-200, 1e-8, 0.01, 0.5, 1.0, a / 2, a, a + 1, a + 3 * math.sqrt(a), 3 * a + 30]:
            log_p, log_q = incomplete.log_gamma_tails(a, math.log(x))
            p, q = special.gammainc(a, x), special.gammaincc(a, x)
            for ours, theirs in ((log_p, p), (log_q, q)):
                if theirs > 1e-280:  # scipy's tails flush to 0 below the normal range
                    want = math.log(theirs)
                    worst = max(worst, abs(ours - want) / max(1.0, abs(want)))
    assert worst < 1e-12, worst


def test_beta_log_tails_agree_with_scipy() -> None:
    worst = 0.0
    for a in SHAPES[:-1]:
        for b in SHAPES[:-1]:
            mean = a / (a + b)
            for y in [1e-100, 1e-6, 0.01, mean / 2, mean, 0.5, (1 + mean) / 2, 0.99]:
                log_i, log_j = incomplete.log_beta_tails(a, b, math.log(y))
                i, j = special.betainc(a, b, y), special.betaincc(a, b, y)
                for ours, theirs in ((log_i, i), (log_j, j)):
                    if theirs > 1e-280:
                        want = math.log(theirs)
                        worst = max(worst, abs(ours - want) / max(1.0, abs(want)))
    assert worst < 1e-12, worst


def test_gamma_inverse_agrees_with_scipy() -> None:
    for a in SHAPES:
        for p in LEVELS:
            x = incomplete.gamma_inverse(a, p, 1.0 - p)
            want = special.gammaincinv(a, p) if p <= 0.5 else special.gammainccinv(a, 1.0 - p)
            assert _relative(x, want) < 2e-13, (a, p, x, want)
            # and the upper tail given exactly (an isf at q = p)
            x = incomplete.gamma_inverse(a, 1.0 - p, p)
            want = special.gammainccinv(a, p)
            assert _relative(x, want) < 2e-13, (a, p, x, want)


def test_beta_inverse_agrees_with_scipy() -> None:
    for a in SHAPES[:-1]:
        for b in SHAPES[:-1]:
            # from 1e-12: deeper, scipy's betaincinv is less accurate than ours (2.7e-10
            # in probability at B(1000, 500), 1e-100); the level test below covers those
            for p in LEVELS[2:]:
                y, w = incomplete.beta_inverse(a, b, p, 1.0 - p)
                want = special.betaincinv(a, b, p)
                if want > 1e-290:
                    assert _relative(y, want) < 2e-13, (a, b, p, y, want)
                # 1 - y to its own accuracy: the upper tail of B(b, a)
                want_w = special.betaincinv(b, a, 1.0 - p) if p > 0.5 else 1.0 - want
                if want_w > 1e-290 and p > 0.5:
                    assert _relative(w, want_w) < 2e-13, (a, b, p, w, want_w)


def test_closed_forms() -> None:
    # P(1, x) = 1 - e^-x; P(1/2, x) = erf(sqrt x); I_y(a, 1) = y^a; I_y(1, b) = 1 - (1-y)^b
    for p in LEVELS:
        q = 1.0 - p
        assert incomplete.gamma_inverse(1.0, p, q) == pytest.approx(-math.log1p(-p), rel=1e-14)
        assert incomplete.gamma_inverse(1.0, q, p) == pytest.approx(-math.log(p), rel=1e-14)
        for a in (0.3, 2.5, 40.0):
            y, _ = incomplete.beta_inverse(a, 1.0, p, q)
            assert y == pytest.approx(math.exp(math.log(p) / a), rel=1e-13)
            _, w = incomplete.beta_inverse(1.0, a, p, q)
            assert w == pytest.approx(math.exp(math.log1p(-p) / a), rel=1e-13)
    for x in (1e-6, 0.25, 2.0, 9.0):
        log_p, _ = incomplete.log_gamma_tails(0.5, math.log(x))
        assert math.exp(log_p) == pytest.approx(math.erf(math.sqrt(x)), rel=1e-13)


def test_large_shapes_are_more_accurate_than_scipys_inverse() -> None:
    # gamma(1e6) at 1e-12: ours lands on the level to 1e-10 by our own (tested) tail;
    # scipy's answer is 1.1e-11 away in x, 8e-8 in probability
    a, p = 1e6, 1e-12
    x = incomplete.gamma_inverse(a, p, 1.0 - p)
    log_p, _ = incomplete.log_gamma_tails(a, math.log(x))
    assert abs(log_p - math.log(p)) < 1e-10
    assert _relative(x, special.gammaincinv(a, p)) < 1e-10
    for a in (1e4, 1e5, 1e6):
        for p in (1e-5, 0.05, 0.5, 0.95):
            x = incomplete.gamma_inverse(a, p, 1.0 - p)
            want = special.gammaincinv(a, p) if p <= 0.5 else special.gammainccinv(a, 1.0 - p)
            assert _relative(x, want) < 1e-10, (a, p)


@settings(max_examples=200, deadline=None)
@given(
    a=st.floats(0.02, 1e4),
    b=st.floats(0.02, 1e4),
    log_p=st.floats(-600.0, math.log(0.5)),
    upper=st.booleans(),
)
def test_inverses_land_on_their_level(a: float, b: float, log_p: float, upper: bool) -> None:
    # the inverse of our own tails, whatever the shapes and level: the log-tail at the
    # quantile is the level to the tail's own error (1e-12 relative, above) plus the
    # iteration's stopping rule (a change of t = log x below 8 ulps of t, i.e. 32 ulps
    # times the log-tail's slope in t, here estimated by a central difference)
    p = math.exp(log_p)
    lower, upper_p = (1.0 - p, p) if upper else (p, 1.0 - p)
    side = 1 if upper else 0

    def check(tail, t: float) -> None:
        slope = abs(tail(t + 1e-6) - tail(t - 1e-6)) / 2e-6
        allowed = 1e-12 * abs(log_p) + 32 * 2.0**-53 * max(1.0, abs(t)) * slope
        assert abs(tail(t) - log_p) <= allowed, (tail(t), log_p, allowed)

    # (a quantile below the normal range has lost digits: its log is not checked)
    x = incomplete.gamma_inverse(a, lower, upper_p)
    if sys.float_info.min < x < math.inf:
        check(lambda t: incomplete.log_gamma_tails(a, t)[side], math.log(x))
    y, w = incomplete.beta_inverse(a, b, lower, upper_p)
    assert y + w == pytest.approx(1.0, abs=1e-15)
    if min(y, w) > sys.float_info.min:
        t = math.log(y) if y <= 0.5 else math.log1p(-w)  # each to its own accuracy
        if t < -1e-6:
            check(lambda t: incomplete.log_beta_tails(a, b, t)[side], t)


def test_quantiles_hand_shapes_beyond_the_limit_to_scipy() -> None:
    big = 3 * incomplete.MAX_SHAPE
    assert quantiles.gamma.ppf(0.3, big) == special.gammaincinv(big, 0.3)
    assert quantiles.gamma.isf(0.3, big) == special.gammainccinv(big, 0.3)
    assert quantiles.f.ppf(0.9, 2.0, 2 * big) == special.fdtri(2.0, 2 * big, 0.9)
    # and below it, not (the quantile is ours, equal to rounding)
    assert quantiles.chi2.ppf(0.99, 22.153) == pytest.approx(
        2 * special.gammaincinv(22.153 / 2, 0.99), rel=2e-13
    )


def test_the_quantiles_of_a_detector_run_need_no_scipy(fresh_python) -> None:
    done = fresh_python(
        "import sys\n"
        "from imufdi_cli.maths.quantiles import chi2, f, gamma\n"
        "chi2.ppf(0.99, 22.15); chi2.isf(1e-5, [1.0, 3.0]); f.ppf(0.99, 1, 174.5)\n"
        "f.isf(1e-4, 42.2, 4198.0); gamma.ppf(0.95, 3.0)\n"
        "print(sorted(m for m in sys.modules if m.startswith('scipy')))\n"
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]"


def test_newton_stops_when_its_step_is_below_rounding(monkeypatch) -> None:
    # a last step smaller than an ulp of t lands on t itself: that is convergence, not a
    # bracket violation to bisect from (which had taken some quantiles 50 evaluations)
    calls = {"beta": 0, "gamma": 0}
    beta_tails, gamma_tails = incomplete._beta_tails, incomplete.log_gamma_tails

    def counted_beta(*args):
        calls["beta"] += 1
        return beta_tails(*args)

    def counted_gamma(*args):
        calls["gamma"] += 1
        return gamma_tails(*args)

    monkeypatch.setattr(incomplete, "_beta_tails", counted_beta)
    monkeypatch.setattr(incomplete, "log_gamma_tails", counted_gamma)
    for cached in (quantiles._f_quantile, quantiles._t_quantile, quantiles._gamma_quantile):
        cached.cache_clear()  # computed here, not recalled from another test's call
    for n, d in ((2.909090909090909, 119.041773166947), (1.6, 106.9), (66.9, 300.0)):
        for p in (0.05, 0.95):
            calls["beta"] = 0
            quantiles.f.ppf(p, n, d)
            assert 1 <= calls["beta"] <= 8, (n, d, p, calls)
    for k in (2.0, 5.3, 44.0):
        for p in (1e-5, 0.05, 0.95):
            calls["gamma"] = 0
            quantiles.chi2.isf(p, k)
            assert 1 <= calls["gamma"] <= 8, (k, p, calls)
