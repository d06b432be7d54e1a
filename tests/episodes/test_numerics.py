"""Numerical helpers of the fits (:mod:`imufdi_cli.episodes.numerics`)."""

from __future__ import annotations

import pytest


def test_fast_quantiles_are_scipy_stats_quantiles(scipy_stats) -> None:
    stats = scipy_stats  # (tests/conftest.py: imported at first use, on the first worker)

    from imufdi_cli.episodes import _chi2_quantile, _f_quantile, _t_quantile

    for p in (0.05, 0.95, 0.999):
        for dof in (1, 5, 47, 1000):
            assert _t_quantile(p, dof) == pytest.approx(stats.t.ppf(p, dof), rel=1e-12)
            assert _chi2_quantile(p, dof) == pytest.approx(stats.chi2.ppf(p, dof), rel=1e-12)
            assert _f_quantile(p, dof, 200) == pytest.approx(stats.f.ppf(p, dof, 200), rel=1e-12)
