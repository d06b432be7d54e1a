"""imufdi_cli.quantiles gives the same floats as scipy.stats, without importing it."""

from __future__ import annotations

import numpy as np
from scipy import stats

from imufdi_cli.quantiles import chi2, f

PROBABILITIES = [0.0, 1e-12, 0.001, 0.05, 0.5, 0.9, 0.95, 0.999, 1 - 1e-9, 1.0]
DOFS = [0.3, 1.0, 1.7, 2.0, 5.0, 12.25, 47.0, 1000.0, 1e6]


# Every grid point in one test (a scalar comparison each; as 210 parametrized cases the
# suite's per-test bookkeeping cost more than the comparisons): a failure lists every
# point that differs.


def test_chi2_ppf_is_scipy_stats_to_the_bit() -> None:
    differ = [
        (q, df) for df in DOFS for q in PROBABILITIES if chi2.ppf(q, df) != stats.chi2.ppf(q, df)
    ]
    assert differ == [], f"chi2.ppf differs from scipy.stats at (q, df) = {differ}"


def test_f_ppf_is_scipy_stats_to_the_bit() -> None:
    differ = [
        (q, dfn, dfd)
        for dfd in [0.8, 3.0, 40.0, 1e5]
        for dfn in [1.0, 2.5, 7.0]
        for q in PROBABILITIES
        if f.ppf(q, dfn, dfd) != stats.f.ppf(q, dfn, dfd)
    ]
    assert differ == [], f"f.ppf differs from scipy.stats at (q, dfn, dfd) = {differ}"


def test_arrays_broadcast_and_invalid_arguments_are_nan_as_in_scipy() -> None:
    q = np.array([[-0.1], [0.0], [0.3], [1.0], [1.5], [np.nan]])
    df = np.array([-1.0, 0.0, 0.5, 4.0, np.nan])
    np.testing.assert_array_equal(chi2.ppf(q, df), stats.chi2.ppf(q, df))
    np.testing.assert_array_equal(f.ppf(q, df, 3.0), stats.f.ppf(q, df, 3.0))
    np.testing.assert_array_equal(f.ppf(q, 2.0, df), stats.f.ppf(q, 2.0, df))


def test_scalars_come_back_as_numpy_scalars() -> None:
    value = chi2.ppf(0.95, 3)
    assert np.ndim(value) == 0 and isinstance(float(value), float)


def test_importing_and_using_it_does_not_import_scipy_stats(quantiles_scipy_modules) -> None:
    # one fresh process with test_special.py's scipy.special check (tests/conftest.py)
    assert "scipy.stats" not in quantiles_scipy_modules
