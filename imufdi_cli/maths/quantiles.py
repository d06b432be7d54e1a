"""Normal, chi-square, F and gamma distribution functions on ``scipy.special``'s public ufuncs.

The detectors' thresholds, the calibration's noise checks and the episode intervals need a
handful of tail probabilities and quantiles of four laws. ``scipy.stats`` gives them, but
its import costs about 0.8 s of CPU (it pulls in ``scipy.linalg``, ``scipy.optimize`` and
``scipy.sparse``), paid by every ``imufdi detect`` for a few numbers, and its generic
``rv_continuous`` wrapper adds tens of microseconds a call. The laws are closed forms of
documented special functions (Abramowitz & Stegun 26.2, 26.4, 26.6; scipy.special's
``ndtr``, ``chdtr``, ``fdtr``, ``gammainc`` families), which ``scipy.special`` exports as
compiled ufuncs for about a third of that import::

    norm   pdf exp(-x^2/2)/sqrt(2 pi)  cdf ndtr(x)              sf ndtr(-x)
           ppf ndtri(q)                isf -ndtri(q)
    chi2   cdf chdtr(k, x)             sf chdtrc(k, x)
           ppf 2 gammaincinv(k/2, q)   isf chdtri(k, q)
    f      cdf fdtr(n, d, x)           sf fdtrc(n, d, x)
           ppf fdtri(n, d, q)          isf fdtri(n, d, 1 - q)
    gamma  cdf gammainc(a, x)          sf gammaincc(a, x)
           ppf gammaincinv(a, q)       isf gammainccinv(a, q)

These are the expressions ``scipy.stats`` evaluates for the same laws, so the values agree
with it to rounding (``tests/maths/test_quantiles.py`` compares them over grids).
``scipy.special`` is imported at the first call, never on import of this module: ``imufdi
--help`` and ``imufdi info`` do not load it.

Every method takes array_like arguments that broadcast, plus keyword ``loc`` (default 0)
and ``scale`` (default 1, > 0): ``x`` is standardised as ``(x - loc) / scale``, a quantile
returned as ``q * scale + loc``, a density divided by ``scale``. Invalid arguments (a
shape parameter <= 0, ``scale <= 0``, a probability outside [0, 1], NaN) give NaN, as the
special functions give it. A scalar call returns a NumPy float64 scalar.
"""

from __future__ import annotations

import math
from types import ModuleType
from typing import Any

import numpy as np

_SQRT_2PI = math.sqrt(2.0 * math.pi)


def _special() -> ModuleType:
    """``scipy.special``, imported at first use (about 0.2 s of CPU over numpy's)."""
    from scipy import special

    return special


def _scale(scale: Any) -> Any:
    """``scale`` as float64, NaN where it is not > 0 (so the result is NaN there)."""
    s = np.asarray(scale, dtype=np.float64)
    return np.where(s > 0, s, np.nan)


def _out(value: Any) -> Any:
    """A NumPy float64 scalar for a zero-dimensional result, else the array."""
    array = np.asarray(value, dtype=np.float64)
    return array[()] if array.ndim == 0 else array


class _Law:
    """A law's cdf, sf, ppf and isf from its standard form (loc 0, scale 1)."""

    def _cdf(self, x: Any, *shapes: Any) -> Any:
        raise NotImplementedError

    def _sf(self, x: Any, *shapes: Any) -> Any:
        raise NotImplementedError

    def _ppf(self, q: Any, *shapes: Any) -> Any:
        raise NotImplementedError

    def _isf(self, q: Any, *shapes: Any) -> Any:
        raise NotImplementedError

    def cdf(self, x: Any, *shapes: Any, loc: Any = 0.0, scale: Any = 1.0) -> Any:
        """``P(X <= x)``."""
        z = (np.asarray(x, dtype=np.float64) - loc) / _scale(scale)
        return _out(self._cdf(z, *shapes))

    def sf(self, x: Any, *shapes: Any, loc: Any = 0.0, scale: Any = 1.0) -> Any:
        """``P(X > x)``, computed directly (accurate far in the upper tail)."""
        z = (np.asarray(x, dtype=np.float64) - loc) / _scale(scale)
        return _out(self._sf(z, *shapes))

    def ppf(self, q: Any, *shapes: Any, loc: Any = 0.0, scale: Any = 1.0) -> Any:
        """The quantile ``x`` with ``P(X <= x) = q``."""
        return _out(self._ppf(np.asarray(q, dtype=np.float64), *shapes) * _scale(scale) + loc)

    def isf(self, q: Any, *shapes: Any, loc: Any = 0.0, scale: Any = 1.0) -> Any:
        """The quantile ``x`` with ``P(X > x) = q`` (accurate for a small ``q``)."""
        return _out(self._isf(np.asarray(q, dtype=np.float64), *shapes) * _scale(scale) + loc)


class _Norm(_Law):
    """The normal law N(loc, scale^2): ``pdf(x)``, ``cdf(x)``, ``sf(x)``, ``ppf(q)``,
    ``isf(q)`` (``scale`` is the standard deviation)."""

    def pdf(self, x: Any, *, loc: Any = 0.0, scale: Any = 1.0) -> Any:
        """The density at ``x``."""
        s = _scale(scale)
        z = (np.asarray(x, dtype=np.float64) - loc) / s
        return _out(np.exp(-(z**2) / 2.0) / _SQRT_2PI / s)

    def _cdf(self, x: Any, *shapes: Any) -> Any:
        return _special().ndtr(x)

    def _sf(self, x: Any, *shapes: Any) -> Any:
        return _special().ndtr(-x)

    def _ppf(self, q: Any, *shapes: Any) -> Any:
        return _special().ndtri(q)

    def _isf(self, q: Any, *shapes: Any) -> Any:
        return -_special().ndtri(q)


class _Chi2(_Law):
    """The chi-square law with ``df`` degrees of freedom (> 0, need not be an integer):
    ``cdf(x, df)``, ``sf(x, df)``, ``ppf(q, df)``, ``isf(q, df)``; support [0, inf)."""

    def _cdf(self, x: Any, *shapes: Any) -> Any:
        return _special().chdtr(shapes[0], np.maximum(x, 0.0))

    def _sf(self, x: Any, *shapes: Any) -> Any:
        return _special().chdtrc(shapes[0], np.maximum(x, 0.0))

    def _ppf(self, q: Any, *shapes: Any) -> Any:
        return 2.0 * _special().gammaincinv(np.asarray(shapes[0], dtype=np.float64) / 2.0, q)

    def _isf(self, q: Any, *shapes: Any) -> Any:
        return _special().chdtri(shapes[0], q)


class _F(_Law):
    """The F law with ``dfn``, ``dfd`` degrees of freedom (> 0): ``cdf(x, dfn, dfd)``,
    ``sf``, ``ppf(q, dfn, dfd)``, ``isf``; support [0, inf)."""

    def _cdf(self, x: Any, *shapes: Any) -> Any:
        return _special().fdtr(shapes[0], shapes[1], np.maximum(x, 0.0))

    def _sf(self, x: Any, *shapes: Any) -> Any:
        return _special().fdtrc(shapes[0], shapes[1], np.maximum(x, 0.0))

    # the quantile at probability 0 is the support's end, 0, for valid degrees of freedom
    # (scipy 1.13's fdtri returns NaN there)
    def _ppf(self, q: Any, *shapes: Any) -> Any:
        at_zero = (np.asarray(q) == 0.0) & (np.asarray(shapes[0]) > 0) & (np.asarray(shapes[1]) > 0)
        return np.where(at_zero, 0.0, _special().fdtri(shapes[0], shapes[1], q))

    def _isf(self, q: Any, *shapes: Any) -> Any:
        at_one = (np.asarray(q) == 1.0) & (np.asarray(shapes[0]) > 0) & (np.asarray(shapes[1]) > 0)
        return np.where(at_one, 0.0, _special().fdtri(shapes[0], shapes[1], 1.0 - q))


class _Gamma(_Law):
    """The gamma law with shape ``a`` (> 0): ``cdf(x, a)``, ``sf``, ``ppf(q, a)``, ``isf``
    (mean ``a * scale``); support [0, inf)."""

    def _cdf(self, x: Any, *shapes: Any) -> Any:
        return _special().gammainc(shapes[0], np.maximum(x, 0.0))

    def _sf(self, x: Any, *shapes: Any) -> Any:
        return _special().gammaincc(shapes[0], np.maximum(x, 0.0))

    def _ppf(self, q: Any, *shapes: Any) -> Any:
        return _special().gammaincinv(shapes[0], q)

    def _isf(self, q: Any, *shapes: Any) -> Any:
        return _special().gammainccinv(shapes[0], q)


#: the normal law
norm = _Norm()
#: the chi-square law
chi2 = _Chi2()
#: Snedecor's F law
f = _F()
#: the gamma law
gamma = _Gamma()

__all__ = ["chi2", "f", "gamma", "norm"]
