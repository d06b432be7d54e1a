"""Normal, chi-square, F, gamma and t distribution functions without ``scipy.stats``.

The detectors' thresholds, the calibration's noise checks and the episode intervals need a
handful of tail probabilities and quantiles of five laws. ``scipy.stats`` gives them, but
its import costs about 0.8 s of CPU (it pulls in ``scipy.linalg``, ``scipy.optimize`` and
``scipy.sparse``), paid by every ``imufdi detect`` for a few numbers, and its generic
``rv_continuous`` wrapper adds tens of microseconds a call. The laws are closed forms of
documented special functions (Abramowitz & Stegun 26.2, 26.4, 26.6)::

    norm   pdf exp(-x^2/2)/sqrt(2 pi)  cdf ndtr(x)              sf ndtr(-x)
           ppf ndtri(q)                isf -ndtri(q)
    chi2   cdf chdtr(k, x)             sf chdtrc(k, x)
           ppf 2 P^-1(k/2, q)          isf 2 Q^-1(k/2, q)
    f      cdf fdtr(n, d, x)           sf fdtrc(n, d, x)
           ppf d y / (n (1 - y)), y = I^-1_q(n/2, d/2)     isf the same at 1 - q
    gamma  cdf gammainc(a, x)          sf gammaincc(a, x)
           ppf P^-1(a, q)              isf Q^-1(a, q)
    t      cdf stdtr(k, x)             sf stdtr(k, -x)
           ppf -+sqrt(F quantile(1, k) at upper tail 2 min(q, 1 - q))    isf ppf(1 - q)

The distribution functions and the normal quantiles are ``scipy.special``'s compiled
ufuncs (``ndtr``, ``chdtr``, ``fdtr``, ``gammainc``, ``stdtr`` families), imported at the first call,
never on import of this module: ``imufdi --help`` and ``imufdi info`` do not load it. The
chi-square, F, gamma and t quantiles, which are what the detectors' thresholds need, are
:mod:`~imufdi_cli.maths.incomplete`'s inverses of the incomplete gamma and beta
functions, in pure Python (importing ``scipy.special`` for them would cost 0.27 s of CPU,
a fifth of ``imufdi detect -d glt`` on a 10-minute log), element by element (about
0.01-0.1 ms each, cached by the callers that repeat them: meant for the few values a run
needs), each tail computed directly (an upper-tail quantile at ``q = 1e-300`` is
accurate); shapes above ``incomplete.MAX_SHAPE`` go to ``scipy.special``. The
distribution functions agree with ``scipy.stats``'s to rounding, the chi-square and gamma
quantiles with its quantiles, and the F and t quantiles invert its distribution functions
to 1e-11 relative (scipy 1.13's own F and t quantiles are off by up to 1e-4:
``tests/maths/test_quantiles.py``; ``tests/maths/test_incomplete.py`` bounds the inverses'
error).

Every method takes array_like arguments that broadcast, plus keyword ``loc`` (default 0)
and ``scale`` (default 1, > 0): ``x`` is standardised as ``(x - loc) / scale``, a quantile
returned as ``q * scale + loc``, a density divided by ``scale``. Invalid arguments (a
shape parameter <= 0, ``scale <= 0``, a probability outside [0, 1], NaN) give NaN, as the
special functions give it. A scalar call returns a NumPy float64 scalar.
"""

from __future__ import annotations

import functools
import math
from types import ModuleType
from typing import Any

import numpy as np

from imufdi_cli.maths import incomplete

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


def _elementwise(function: Any, q: Any, *shapes: Any, upper: bool) -> Any:
    """``function(lower, upper, *shapes)`` of every element of the broadcast arguments, with
    ``(lower, upper) = (1 - q, q)`` for an upper-tail quantile, else ``(q, 1 - q)``."""
    arrays = np.broadcast_arrays(np.asarray(q, dtype=np.float64), *shapes)
    out = np.empty(arrays[0].shape, dtype=np.float64)
    flat = out.reshape(-1)
    columns = [np.asarray(a, dtype=np.float64).reshape(-1).tolist() for a in arrays]
    for i, (p, *values) in enumerate(zip(*columns)):
        flat[i] = function(1.0 - p, p, *values) if upper else function(p, 1.0 - p, *values)
    return out


def _valid(lower: float, *shapes: float) -> bool:
    """A probability in [0, 1] and positive shapes (False for NaN)."""
    return 0.0 <= lower <= 1.0 and all(s > 0.0 for s in shapes)


@functools.lru_cache(maxsize=4096)  # the degrees of freedom that repeat in a run
def _gamma_quantile(lower: float, upper: float, a: float) -> float:
    """The standard gamma quantile with lower tail ``lower`` (``upper = 1 - lower``)."""
    if not _valid(lower, a):
        return math.nan
    if lower == 0.0 or upper == 0.0:
        return 0.0 if lower == 0.0 else math.inf
    if a > incomplete.MAX_SHAPE:
        special = _special()
        return float(
            special.gammaincinv(a, lower) if lower <= upper else special.gammainccinv(a, upper)
        )
    return incomplete.gamma_inverse(a, lower, upper)


@functools.lru_cache(maxsize=4096)  # the degrees of freedom that repeat in a run
def _f_quantile(lower: float, upper: float, dfn: float, dfd: float) -> float:
    """The F quantile with lower tail ``lower``: ``d y / (n (1 - y))`` for the beta law's
    ``y`` of shapes ``(n/2, d/2)`` (A&S 26.6.2)."""
    if not _valid(lower, dfn, dfd):
        return math.nan
    if lower == 0.0 or upper == 0.0:
        return 0.0 if lower == 0.0 else math.inf
    if max(dfn, dfd) / 2.0 > incomplete.MAX_SHAPE:
        return float(_special().fdtri(dfn, dfd, lower))
    y, w = incomplete.beta_inverse(dfn / 2.0, dfd / 2.0, lower, upper)
    return dfd * y / (dfn * w) if w > 0.0 else math.inf


@functools.lru_cache(maxsize=4096)  # the degrees of freedom that repeat in a run
def _t_quantile(lower: float, upper: float, dof: float) -> float:
    """The t quantile with lower tail ``lower``: ``+-sqrt`` of the F(1, dof) quantile whose
    upper tail is twice the smaller of ``lower`` and ``upper`` (exact in floating point)."""
    if not _valid(lower, dof):
        return math.nan
    if lower == upper:
        return 0.0
    two_tails = 2.0 * min(lower, upper)
    size = math.sqrt(_f_quantile(1.0 - two_tails, two_tails, 1.0, dof))
    return size if lower > upper else -size


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
        return 2.0 * _elementwise(_gamma_quantile, q, np.asarray(shapes[0]) / 2.0, upper=False)

    def _isf(self, q: Any, *shapes: Any) -> Any:
        return 2.0 * _elementwise(_gamma_quantile, q, np.asarray(shapes[0]) / 2.0, upper=True)


class _F(_Law):
    """The F law with ``dfn``, ``dfd`` degrees of freedom (> 0): ``cdf(x, dfn, dfd)``,
    ``sf``, ``ppf(q, dfn, dfd)``, ``isf``; support [0, inf)."""

    def _cdf(self, x: Any, *shapes: Any) -> Any:
        return _special().fdtr(shapes[0], shapes[1], np.maximum(x, 0.0))

    def _sf(self, x: Any, *shapes: Any) -> Any:
        return _special().fdtrc(shapes[0], shapes[1], np.maximum(x, 0.0))

    def _ppf(self, q: Any, *shapes: Any) -> Any:
        return _elementwise(_f_quantile, q, shapes[0], shapes[1], upper=False)

    def _isf(self, q: Any, *shapes: Any) -> Any:
        return _elementwise(_f_quantile, q, shapes[0], shapes[1], upper=True)


class _T(_Law):
    """Student's t law with ``df`` degrees of freedom (> 0): ``cdf(x, df)``, ``sf``,
    ``ppf(q, df)``, ``isf``; its quantiles from F(1, df), ``t^2 ~ F(1, df)`` (A&S 26.7.1)."""

    def _cdf(self, x: Any, *shapes: Any) -> Any:
        return _special().stdtr(shapes[0], x)

    def _sf(self, x: Any, *shapes: Any) -> Any:
        return _special().stdtr(shapes[0], -np.asarray(x))

    def _ppf(self, q: Any, *shapes: Any) -> Any:
        return _elementwise(_t_quantile, q, shapes[0], upper=False)

    def _isf(self, q: Any, *shapes: Any) -> Any:
        return _elementwise(_t_quantile, q, shapes[0], upper=True)


class _Gamma(_Law):
    """The gamma law with shape ``a`` (> 0): ``cdf(x, a)``, ``sf``, ``ppf(q, a)``, ``isf``
    (mean ``a * scale``); support [0, inf)."""

    def _cdf(self, x: Any, *shapes: Any) -> Any:
        return _special().gammainc(shapes[0], np.maximum(x, 0.0))

    def _sf(self, x: Any, *shapes: Any) -> Any:
        return _special().gammaincc(shapes[0], np.maximum(x, 0.0))

    def _ppf(self, q: Any, *shapes: Any) -> Any:
        return _elementwise(_gamma_quantile, q, shapes[0], upper=False)

    def _isf(self, q: Any, *shapes: Any) -> Any:
        return _elementwise(_gamma_quantile, q, shapes[0], upper=True)


#: the normal law
norm = _Norm()
#: the chi-square law
chi2 = _Chi2()
#: Snedecor's F law
f = _F()
#: the gamma law
gamma = _Gamma()
#: Student's t law
t = _T()

__all__ = ["chi2", "f", "gamma", "norm", "t"]
