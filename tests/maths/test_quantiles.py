"""imufdi_cli.maths.quantiles: the normal, chi-square, F, gamma and t laws.

scipy.stats is the independent oracle here, imported at first use through the session
fixture ``scipy_stats`` (tests/conftest.py), so that only the worker running these tests
pays its import.

Tolerance of the comparisons with scipy.stats, ``rtol = 1e-12``:
- the densities, distribution functions and normal quantiles evaluate the same compiled
  special function on the same standardised argument, so they agree to rounding; the
  tolerance leaves room for a scipy release that computes the standardisation
  ``(x - loc) / scale`` or a complement ``1 - q`` in another order (one ulp of the
  argument, times the function's condition number on these grids: below 1e-13);
- the chi-square, F, gamma and t quantiles are this project's own (maths/incomplete.py),
  within 2e-13 of scipy's on these grids (tests/maths/test_incomplete.py bounds the
  difference over wider ones);
and none for a wrong law, tail or degree-of-freedom convention (those are off by more
than 1e-3).

The F and t quantiles are checked through scipy's distribution functions instead of its
quantiles, which are not accurate enough to be an oracle: scipy 1.13's ``f.ppf`` and
``t.ppf`` are off by up to 1e-4 relative (``f.ppf(1e-12, 2, 2)`` is 2.0e-24 exactly, scipy
1.13 gives 1.99991e-24; ``t.ppf(0.05, 1)`` is ``-cot(pi/20)``, 2e-11 away from scipy
1.13's), ``f.isf`` inverts the distribution function at ``1 - q`` and loses the small
tail, and at 1e-300 ``t.ppf`` has the wrong sign. The round trip takes an upper tail as
the lower tail of the reflected law (``-X`` for t, ``1/X ~ F(d, n)`` for F), as scipy's
``sf`` also loses it far out, and measures the quantile's
relative error as ``|tail(x) - q| / (|x| pdf(x))``, the distribution function's error
``(about 1e-15 of the tail) mapped through its slope``, against ``1e-11`` (which leaves a
factor 10 for the slope's amplification in the far tails of these grids). The F law's
closed forms with two numerator degrees of freedom check the 1e-300 tail directly.
"""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose

from imufdi_cli.maths import quantiles
from imufdi_cli.maths.quantiles import chi2, f

RTOL = 1e-12  # module docstring

#: points inside and at the edge of the support, with a moderate tail (module docstring)
POINTS = np.array([-40.0, -9.0, -1.5, -1e-300, 0.0, 1e-300, 1e-12, 0.3, 1.0, 2.5, 7.0, 40.0])
LEVELS = np.array([0.0, 1e-300, 1e-12, 0.001, 0.05, 0.5, 0.9, 0.95, 0.999, 1 - 1e-9, 1.0])
SHAPES = np.array([0.3, 1.0, 1.7, 2.0, 5.0, 12.25, 47.0, 1000.0])
#: (loc, scale): the default and a shifted, scaled law
LOC_SCALE = [(0.0, 1.0), (0.5, 2.0)]

FUNCTIONS = [("norm", 0, method) for method in ("pdf", "cdf", "sf", "ppf", "isf")] + [
    (name, n, method)
    for name, n in (("chi2", 1), ("f", 2), ("gamma", 1), ("t", 1))
    for method in (("cdf", "sf", "ppf", "isf") if name in ("chi2", "gamma") else ("cdf", "sf"))
]


@pytest.mark.parametrize(("name", "n_shapes", "method"), FUNCTIONS)
def test_every_function_agrees_with_scipy_stats_over_a_grid(
    scipy_stats, name: str, n_shapes: int, method: str
) -> None:
    values = POINTS if method in ("pdf", "cdf", "sf") else LEVELS
    x = np.reshape(values, (-1,) + (1,) * n_shapes)
    shapes = [
        np.reshape(SHAPES, (1,) * (1 + k) + (-1,) + (1,) * (n_shapes - 1 - k))
        for k in range(n_shapes)
    ]
    ours = getattr(getattr(quantiles, name), method)
    theirs = getattr(getattr(scipy_stats, name), method)
    for loc, scale in LOC_SCALE:
        got = ours(x, *shapes, loc=loc, scale=scale)
        want = theirs(x, *shapes, loc=loc, scale=scale)
        assert got.shape == want.shape == (len(values),) + (len(SHAPES),) * n_shapes
        assert_allclose(
            got,
            want,
            rtol=RTOL,
            atol=0.0,
            err_msg=f"{name}.{method} {loc} {scale}",
        )


@pytest.mark.parametrize(("name", "method"), [(n, m) for n in ("f", "t") for m in ("ppf", "isf")])
def test_f_and_t_quantiles_invert_scipys_distribution_functions(
    scipy_stats, name: str, method: str
) -> None:
    law, theirs = getattr(quantiles, name), getattr(scipy_stats, name)
    n_shapes = 2 if name == "f" else 1

    def upper_tail(x: float, *shapes: float) -> float:
        # P(X > x) = P(-X < -x) for t, P(1/X < 1/x) with 1/X ~ F(d, n) (A&S 26.6.3)
        if name == "t":
            return float(theirs.cdf(-x, *shapes))
        return float(theirs.cdf(1.0 / x, shapes[1], shapes[0]))

    worst = 0.0
    for q in LEVELS:
        for shapes in np.broadcast(*([SHAPES[:, None], SHAPES[None, :]][:n_shapes])):
            x = float(getattr(law, method)(q, *shapes))
            if q in (0.0, 1.0):  # the support's ends
                assert x == float(getattr(theirs, method)(q, *shapes)), (q, shapes)
                continue
            if x == 0.0 or not np.isfinite(x):  # underflow or overflow of the quantile
                continue
            # the smaller tail, its level given exactly (q itself when q <= 0.5)
            small, level = (method == "ppf") == (q <= 0.5), min(q, 1.0 - q)
            # (the upper tail as a lower one: scipy's sf loses it far out)
            tail = float(theirs.cdf(x, *shapes)) if small else upper_tail(x, *shapes)
            if tail == 0.0:  # scipy's function underflows there (1e-300, large shapes)
                continue
            error = tail - level
            density = abs(x) * float(theirs.pdf(x, *shapes))
            if density > 0.0:
                worst = max(worst, abs(error) / density)
    assert worst < 1e-11, worst
    # loc and scale: the standard quantile moved and stretched
    assert law.ppf(0.9, *[5.0] * n_shapes, loc=0.5, scale=2.0) == 0.5 + 2.0 * law.ppf(
        0.9, *[5.0] * n_shapes
    )


def test_f_quantiles_far_in_the_tails_match_the_closed_forms() -> None:
    # F(2, d): sf(x) = (1 + 2x/d)^(-d/2), so isf(q) = d/2 (q^(-2/d) - 1) and
    # ppf(q) = d/2 (expm1(-(2/d) log1p(-q))); both well conditioned at q = 1e-300
    # (tolerance: the closed forms' own rounding, a few ulps, times log(1e300) ~ 690 at
    # most for the power)
    d = np.array([0.3, 1.0, 2.0, 5.0, 47.0, 1000.0])
    for q in (1e-300, 1e-100, 1e-12):
        with np.errstate(over="ignore"):  # beyond the largest float: inf, as ours gives
            isf = d / 2 * np.expm1(-(2 / d) * np.log(q))
        ppf = d / 2 * np.expm1(-(2 / d) * np.log1p(-q))
        assert_allclose(f.isf(q, 2.0, d), isf, rtol=1e-13, atol=0.0)
        assert_allclose(f.ppf(q, 2.0, d), ppf, rtol=1e-13, atol=0.0)
    # and where the quantile underflows it is 0, not a tiny positive number
    assert f.ppf(1e-300, 0.3, 5.0) == 0.0


def test_the_detectors_array_calls_agree_with_scipy_stats(scipy_stats) -> None:
    # the calls of noise_glr.py, cnn_map/mapping.py and calibrate/noise.py, in their shapes
    counts = np.arange(1, 201, dtype=np.float64)
    shapes = 3.7 * counts / 200
    grid = np.linspace(-12.0, 12.0, 24001)
    recent, older = counts[:20, None], np.maximum(np.arange(0, 50), 1)[None, :] * 1.0
    pairs = [
        (
            quantiles.gamma.ppf(1 - 1e-4, shapes, scale=1.3 / shapes),
            scipy_stats.gamma.ppf(1 - 1e-4, shapes, scale=1.3 / shapes),
        ),
        (quantiles.norm.pdf(grid), scipy_stats.norm.pdf(grid)),
        (quantiles.norm.cdf(grid), scipy_stats.norm.cdf(grid)),
        (quantiles.norm.sf(grid), scipy_stats.norm.sf(grid)),
        (quantiles.chi2.isf(1e-5, counts), scipy_stats.chi2.isf(1e-5, counts)),
        (quantiles.f.ppf(0.01, recent, older), scipy_stats.f.ppf(0.01, recent, older)),
        (quantiles.f.sf(grid[::100] ** 2, 3, 40.5), scipy_stats.f.sf(grid[::100] ** 2, 3, 40.5)),
    ]
    for i, (ours, theirs) in enumerate(pairs):
        assert_allclose(ours, theirs, rtol=RTOL, atol=0.0, err_msg=str(i))


def test_scalars_come_back_as_float64_scalars() -> None:
    for value in (quantiles.norm.pdf(0.5), chi2.ppf(0.99, 3), f.sf(2.0, 1, 9), chi2.cdf(3, 2)):
        assert type(value) is np.float64


def test_support_ends_and_invalid_arguments() -> None:
    # below the support: cdf 0, sf 1; the quantiles' ends: the support's ends
    assert chi2.cdf(-1.0, 3) == 0.0 and chi2.sf(-1.0, 3) == 1.0
    assert f.cdf(-1.0, 2, 5) == 0.0 and quantiles.gamma.sf(-2.0, 2.0) == 1.0
    assert chi2.ppf(0.0, 3) == 0.0 and chi2.ppf(1.0, 3) == np.inf and chi2.isf(0.0, 3) == np.inf
    assert quantiles.norm.ppf(0.0) == -np.inf and quantiles.norm.isf(0.0) == np.inf
    # invalid: a probability outside [0, 1], a scale <= 0, NaN
    with np.errstate(invalid="ignore"):
        assert np.isnan(chi2.ppf(1.5, 3)) and np.isnan(f.ppf(-0.1, 2, 5))
        assert np.isnan(quantiles.norm.cdf(0.0, scale=0.0))
        assert np.isnan(quantiles.gamma.ppf(0.5, 2.0, scale=-1.0))
        assert np.isnan(chi2.sf(np.nan, 3)) and np.isnan(quantiles.norm.pdf(np.nan))
        assert np.isnan(chi2.ppf(0.5, -1.0))
    # arrays broadcast, invalid elements NaN and the others computed
    with np.errstate(invalid="ignore"):
        got = chi2.ppf(np.array([[0.3], [1.5]]), np.array([1.0, 4.0]))
    assert got.shape == (2, 2) and np.isnan(got[1]).all() and np.isfinite(got[0]).all()


def test_known_values() -> None:
    # textbook quantiles, independently of scipy: z_0.975, chi2_0.95(1) = z_0.975^2,
    # the median of chi2(2) = 2 ln 2, F(1, nu) = t(nu)^2: F_0.95(1, 10) = 2.228139^2
    # (tolerances: a few ulps of the special functions' documented accuracy)
    assert quantiles.norm.ppf(0.975) == pytest.approx(1.959963984540054, rel=1e-14)
    assert chi2.isf(0.05, 1) == pytest.approx(1.959963984540054**2, rel=1e-13)
    assert chi2.ppf(0.5, 2) == pytest.approx(2 * np.log(2), rel=1e-14)
    assert f.ppf(0.95, 1, 10) == pytest.approx(2.228138851986274**2, rel=1e-12)
    assert quantiles.gamma.ppf(0.5, 1, scale=3.0) == pytest.approx(3 * np.log(2), rel=1e-14)
    assert quantiles.norm.pdf(0.0) == pytest.approx(1 / np.sqrt(2 * np.pi), rel=1e-15)
    assert quantiles.norm.sf(1.0, loc=1.0, scale=5.0) == 0.5
    # t: the Cauchy law at 1 dof, tan(pi (q - 1/2)) = -1 / tan(pi q) (the second form for
    # a small q, where q - 1/2 would round); t_0.975(10) = 2.228139 (tables)
    for q in (1e-12, 0.01, 0.3, 0.5, 0.9, 0.999):
        cauchy = -1 / np.tan(np.pi * q) if q < 0.25 else np.tan(np.pi * (q - 0.5))
        assert quantiles.t.ppf(q, 1.0) == pytest.approx(cauchy, rel=1e-12)
    assert quantiles.t.ppf(0.975, 10) == pytest.approx(2.228138851986274, rel=1e-13)
    # (1 - 0.975 is 0.025 to 1e-15: the two differ by that much)
    assert quantiles.t.isf(0.025, 10) == pytest.approx(quantiles.t.ppf(0.975, 10), rel=1e-14)


def test_importing_it_imports_no_scipy_and_using_it_not_scipy_stats(fresh_python) -> None:
    done = fresh_python(
        "import sys\n"
        "from imufdi_cli.maths.quantiles import chi2, f, gamma, norm\n"
        "print(sorted(m for m in sys.modules if m.startswith('scipy')))\n"
        "chi2.ppf(0.99, 3); f.ppf(0.99, 1, 50); gamma.isf(0.3, 2.0); norm.sf(1.0)\n"
        "print('scipy.special' in sys.modules, 'scipy.stats' in sys.modules)\n"
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == ["[]", "True False"]
