"""Numerical helpers of the fits (:mod:`imufdi_cli.episodes.numerics`)."""

from __future__ import annotations

import pytest


def test_fast_quantiles_are_the_laws_quantiles(scipy_stats) -> None:
    """The cached quantiles are maths.quantiles' (tested there against scipy's distribution
    functions). Here: each is the quantile of its law, checked through scipy's
    distribution functions (their error, about 1e-15 of the tail, is the tolerance on the
    level; scipy's own t and F quantiles are not accurate enough to be the oracle on every
    supported scipy: tests/maths/test_quantiles.py)."""
    stats = scipy_stats  # (tests/conftest.py: imported at first use, on the first worker)

    from imufdi_cli.episodes import _chi2_quantile, _f_quantile, _t_quantile

    for p in (0.05, 0.95, 0.999):
        for dof in (1, 5, 47, 1000):
            assert stats.t.cdf(_t_quantile(p, dof), dof) == pytest.approx(p, rel=1e-13)
            assert stats.chi2.cdf(_chi2_quantile(p, dof), dof) == pytest.approx(p, rel=1e-13)
            assert stats.f.cdf(_f_quantile(p, dof, 200), dof, 200) == pytest.approx(p, rel=1e-13)
    # and a closed form: t(1) is Cauchy, t_0.05(1) = -cot(pi / 20)
    assert _t_quantile(0.05, 1) == pytest.approx(-1 / 0.15838444032453627, rel=1e-14)
