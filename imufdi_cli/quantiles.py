"""Chi-square and F quantiles without importing ``scipy.stats``.

``scipy.stats`` costs about 1 s of CPU to import on the build machine (issue 20: ``imufdi
detect -d glt`` paid it for two ``ppf`` calls at calibration). Its ``chi2.ppf`` and
``f.ppf`` evaluate ``2 gammaincinv(df / 2, q)`` and ``fdtri(dfn, dfd, q)`` from
``scipy.special`` (scipy 1.17 ``stats/_continuous_distns.py``: ``chi2_gen._ppf``,
``f_gen._ppf``), after checking their arguments. :data:`chi2` and :data:`f` here evaluate
the same functions with the same argument rules, so their results are the same floats
(``tests/test_quantiles.py`` compares them bit for bit); ``scipy.special`` imports in about
a third of the time, and its compiled ufuncs alone (:mod:`imufdi_cli.special`) in a tenth
of that.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from imufdi_cli.special import ufunc


def _finish(q: np.ndarray, valid: np.ndarray, values: np.ndarray) -> Any:
    """scipy.stats' boundary rules: 0 at q = 0, inf at q = 1, NaN for invalid arguments;
    a NumPy scalar for scalar arguments."""
    out = np.where(valid & (q == 0), 0.0, np.where(valid & (q == 1), np.inf, values))
    out = np.where(valid & (q >= 0) & (q <= 1), out, np.nan)
    return out[()]


class _Chi2:
    """The chi-square distribution's quantile function, as ``scipy.stats.chi2.ppf``."""

    def ppf(self, q: Any, df: Any) -> Any:
        """Quantile ``x`` with ``P(X <= x) = q`` for X ~ chi2(df).

        Parameters
        ----------
        q : float or array_like
            Lower-tail probability in [0, 1].
        df : float or array_like
            Degrees of freedom (> 0, need not be an integer); broadcast against ``q``.

        Returns
        -------
        numpy.float64 or ndarray
            ``2 gammaincinv(df / 2, q)``; NaN where ``q`` or ``df`` is out of range.
        """
        gammaincinv = ufunc("gammaincinv")  # scipy.special's, without its import

        q, df = np.broadcast_arrays(np.asarray(q, np.float64), np.asarray(df, np.float64))
        valid = df > 0
        with np.errstate(invalid="ignore"):
            values = 2 * gammaincinv(np.where(valid, df, 1.0) / 2, np.clip(q, 0.0, 1.0))
        return _finish(q, valid, values)


class _F:
    """The F distribution's quantile function, as ``scipy.stats.f.ppf``."""

    def ppf(self, q: Any, dfn: Any, dfd: Any) -> Any:
        """Quantile ``x`` with ``P(X <= x) = q`` for X ~ F(dfn, dfd).

        Parameters
        ----------
        q : float or array_like
            Lower-tail probability in [0, 1].
        dfn, dfd : float or array_like
            Numerator and denominator degrees of freedom (> 0); broadcast against ``q``.

        Returns
        -------
        numpy.float64 or ndarray
            ``fdtri(dfn, dfd, q)``; NaN where an argument is out of range.
        """
        fdtri = ufunc("fdtri")  # scipy.special's, without its import

        q, dfn, dfd = np.broadcast_arrays(
            np.asarray(q, np.float64), np.asarray(dfn, np.float64), np.asarray(dfd, np.float64)
        )
        valid = (dfn > 0) & (dfd > 0)
        with np.errstate(invalid="ignore"):
            values = fdtri(
                np.where(valid, dfn, 1.0), np.where(valid, dfd, 1.0), np.clip(q, 0.0, 1.0)
            )
        return _finish(q, valid, values)


#: ``chi2.ppf(q, df)``, the same floats as ``scipy.stats.chi2.ppf``.
chi2 = _Chi2()
#: ``f.ppf(q, dfn, dfd)``, the same floats as ``scipy.stats.f.ppf``.
f = _F()

__all__ = ["chi2", "f"]
