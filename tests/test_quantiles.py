"""imufdi_cli.quantiles gives the same floats as scipy.stats, without importing it.

scipy.stats is the independent oracle here, imported at first use through the session
fixture ``scipy_stats`` (tests/conftest.py), so that only the worker running these tests
pays its import.
"""

from __future__ import annotations

import numpy as np
import pytest

from imufdi_cli import quantiles
from imufdi_cli.quantiles import chi2, f

PROBABILITIES = [0.0, 1e-12, 0.001, 0.05, 0.5, 0.9, 0.95, 0.999, 1 - 1e-9, 1.0]
DOFS = [0.3, 1.0, 1.7, 2.0, 5.0, 12.25, 47.0, 1000.0, 1e6]

# Arguments of the broadcast grids below: inside and outside the support and [0, 1], the
# boundaries, signed zeros, infinities and NaN.
POINTS = [-np.inf, -40.0, -9.0, -1.5, -1e-300, -0.0, 0.0, 1e-300, 1e-12, 0.3, 1.0, 2.5]
POINTS += [7.0, 40.0, 1e3, np.inf, np.nan]
LEVELS = [-0.1, 0.0, 1e-300, 1e-12, 0.001, 0.05, 0.5, 0.9, 0.95, 0.999, 1 - 1e-9, 1.0]
LEVELS += [1.5, np.nan]
SHAPES = [-1.0, 0.0, 0.3, 1.0, 1.7, 2.0, 5.0, 12.25, 47.0, 1000.0, 1e6, np.inf, np.nan]
#: (loc, scale): the default, a shifted and scaled law, and invalid ones
LOC_SCALE = [(0.0, 1.0), (0.5, 2.0), (0.0, -1.0), (np.nan, 1.0), (0.0, 0.0)]

FUNCTIONS = [("norm", 0, method) for method in ("pdf", "cdf", "sf", "ppf", "isf")] + [
    (name, n, method)
    for name, n in (("chi2", 1), ("f", 2), ("gamma", 1))
    for method in (
        "cdf",
        "sf",
        "ppf",
        "isf",
    )
]


def _same(a: object, b: object) -> bool:
    """The same type, dtype, shape and bytes (so -0.0 differs from 0.0, NaN equals NaN)."""
    x, y = np.asarray(a), np.asarray(b)
    return (
        type(a) is type(b)
        and x.dtype == y.dtype
        and x.shape == y.shape
        and (x.tobytes() == y.tobytes())
    )


@pytest.mark.parametrize(("name", "n_shapes", "method"), FUNCTIONS)
def test_every_function_is_scipy_stats_to_the_bit_over_a_grid(
    scipy_stats, name: str, n_shapes: int, method: str
) -> None:
    # one broadcast call over (argument, shape(s), loc/scale) per function
    values = POINTS if method in ("pdf", "cdf", "sf") else LEVELS
    dims = 2 + n_shapes
    x = np.reshape(values, (-1,) + (1,) * (dims - 1))
    shapes = [
        np.reshape(SHAPES, (1,) * (1 + k) + (-1,) + (1,) * (n_shapes - k)) for k in range(n_shapes)
    ]
    loc = np.reshape([ls[0] for ls in LOC_SCALE], (1,) * (dims - 1) + (-1,))
    scale = np.reshape([ls[1] for ls in LOC_SCALE], (1,) * (dims - 1) + (-1,))
    ours = getattr(getattr(quantiles, name), method)
    theirs = getattr(getattr(scipy_stats, name), method)
    with np.errstate(all="ignore"):
        got, want = ours(x, *shapes, loc=loc, scale=scale), theirs(x, *shapes, loc=loc, scale=scale)
        plain_got, plain_want = ours(x, *shapes), theirs(x, *shapes)
    assert got.shape == (len(values),) + (len(SHAPES),) * n_shapes + (len(LOC_SCALE),)
    differ = np.argwhere(got.view(np.uint64) != want.view(np.uint64))
    assert differ.size == 0, f"{name}.{method} differs at grid indices {differ[:10].tolist()}"
    assert _same(plain_got, plain_want)


@pytest.mark.parametrize(("name", "n_shapes", "method"), FUNCTIONS)
def test_scalars_come_back_as_numpy_scalars_as_in_scipy(
    scipy_stats, name: str, n_shapes: int, method: str
) -> None:
    ours = getattr(getattr(quantiles, name), method)
    theirs = getattr(getattr(scipy_stats, name), method)
    shapes = (3.0, 7.5)[:n_shapes]
    for value in (0.0, 0.25, 1.0, 3, np.nan):  # (an int argument: promoted to float64)
        assert _same(ours(value, *shapes), theirs(value, *shapes)), value
    assert _same(ours(0.5, *shapes, loc=1.0, scale=4.0), theirs(0.5, *shapes, loc=1, scale=4))
    assert _same(ours(0.5, *shapes, 1.0, 4.0), theirs(0.5, *shapes, 1.0, 4.0))  # positional
    assert _same(ours(0.5, *shapes, -1.0, scale=4.0), theirs(0.5, *shapes, -1.0, scale=4.0))


def test_the_detectors_array_calls_are_scipy_stats_to_the_bit(scipy_stats) -> None:
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
    assert [i for i, (a, b) in enumerate(pairs) if not _same(a, b)] == []


# Every grid point in one test (a scalar comparison each; as 210 parametrized cases the
# suite's per-test bookkeeping cost more than the comparisons): a failure lists every
# point that differs.


def test_chi2_ppf_is_scipy_stats_to_the_bit(scipy_stats) -> None:
    differ = [
        (q, df)
        for df in DOFS
        for q in PROBABILITIES
        if chi2.ppf(q, df) != scipy_stats.chi2.ppf(q, df)
    ]
    assert differ == [], f"chi2.ppf differs from scipy.stats at (q, df) = {differ}"


def test_f_ppf_is_scipy_stats_to_the_bit(scipy_stats) -> None:
    differ = [
        (q, dfn, dfd)
        for dfd in [0.8, 3.0, 40.0, 1e5]
        for dfn in [1.0, 2.5, 7.0]
        for q in PROBABILITIES
        if f.ppf(q, dfn, dfd) != scipy_stats.f.ppf(q, dfn, dfd)
    ]
    assert differ == [], f"f.ppf differs from scipy.stats at (q, dfn, dfd) = {differ}"


def test_arrays_broadcast_and_invalid_arguments_are_nan_as_in_scipy(scipy_stats) -> None:
    q = np.array([[-0.1], [0.0], [0.3], [1.0], [1.5], [np.nan]])
    df = np.array([-1.0, 0.0, 0.5, 4.0, np.nan])
    np.testing.assert_array_equal(chi2.ppf(q, df), scipy_stats.chi2.ppf(q, df))
    np.testing.assert_array_equal(f.ppf(q, df, 3.0), scipy_stats.f.ppf(q, df, 3.0))
    np.testing.assert_array_equal(f.ppf(q, 2.0, df), scipy_stats.f.ppf(q, 2.0, df))


def test_known_values() -> None:
    # textbook quantiles, independently of scipy: z_0.975, chi2_0.95(1) = z_0.975^2,
    # the median of chi2(2) = 2 ln 2, F(1, nu) = t(nu)^2: F_0.95(1, 10) = 2.228139^2
    assert quantiles.norm.ppf(0.975) == pytest.approx(1.959963984540054, rel=1e-15)
    assert chi2.isf(0.05, 1) == pytest.approx(1.959963984540054**2, rel=1e-14)
    assert chi2.ppf(0.5, 2) == pytest.approx(2 * np.log(2), rel=1e-15)
    assert f.ppf(0.95, 1, 10) == pytest.approx(2.228138851986274**2, rel=1e-13)
    assert quantiles.gamma.ppf(0.5, 1, scale=3.0) == pytest.approx(3 * np.log(2), rel=1e-15)
    assert quantiles.norm.pdf(0.0) == pytest.approx(1 / np.sqrt(2 * np.pi), rel=1e-16)


def test_wrong_or_repeated_arguments_are_a_type_error() -> None:
    with pytest.raises(TypeError):
        chi2.ppf(0.5)
    with pytest.raises(TypeError):
        f.sf(1.0, 3.0)
    with pytest.raises(TypeError):
        quantiles.norm.cdf(0.0, 1.0, 2.0, 3.0)
    with pytest.raises(TypeError):
        chi2.isf(0.5, 2.0, loc=1.0, df=3.0)
    with pytest.raises(TypeError):
        chi2.isf(0.5, 2.0, 1.0, loc=1.0)


def test_importing_and_using_it_does_not_import_scipy_stats(quantiles_scipy_modules) -> None:
    # one fresh process with test_special.py's scipy.special check (tests/conftest.py)
    assert "scipy.stats" not in quantiles_scipy_modules
