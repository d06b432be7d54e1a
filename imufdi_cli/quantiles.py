"""Normal, chi-square, F and gamma distribution functions without importing ``scipy.stats``.

``scipy.stats`` costs 1.0-1.4 s of CPU to import on the build machine (every ``imufdi detect -d bank|noise-glr|pca-parity|cnn-map|woa-mvmd-glt``, ``calibrate``
and ``tune`` paid it for a handful of thresholds, and so did every test process that
imported a detector). Its distributions evaluate compiled functions of ``scipy.special``
(scipy 1.17 ``stats/_continuous_distns.py``)::

    norm   pdf exp(-x**2/2.0) / sqrt(2 pi)   cdf ndtr(x)        sf ndtr(-x)
           ppf ndtri(q)                      isf -ndtri(q)
    chi2   cdf chdtr(df, x)                  sf chdtrc(df, x)
           ppf 2*gammaincinv(df/2, q)        isf chdtri(df, q)
    f      cdf fdtr(dfn, dfd, x)             sf fdtrc(dfn, dfd, x)
           ppf fdtri(dfn, dfd, q)            isf fdtri(dfn, dfd, 1.0 - q)  (generic _isf)
    gamma  cdf gammainc(a, x)                sf gammaincc(a, x)
           ppf gammaincinv(a, q)             isf gammainccinv(a, q)

inside the generic wrapper of ``rv_continuous`` (``stats/_distn_infrastructure.py``:
``pdf``, ``cdf``, ``sf``, ``ppf``, ``isf``), which standardises ``x`` as
``(x - loc) / scale``, checks the shape parameters (all > 0 here) and ``scale > 0``, gives
the boundary values (0 or 1 outside the support; the support's ends at q = 0 and 1), NaN
for invalid arguments, evaluates the function only on the valid elements (``argsreduce``:
the same one-dimensional arrays), then ``* scale + loc`` (quantiles) or ``/ scale``
(density), and returns a NumPy scalar for scalar arguments. The objects here follow that
wrapper step for step with the same compiled ufuncs (:mod:`imufdi_cli.special` loads them
without the ``scipy.special`` package), so their results are the same floats, bit for bit
(``tests/test_quantiles.py`` compares them with scipy.stats over grids including the
boundaries and invalid arguments). Arguments are float64 (other dtypes are converted).

The library's thresholds come from here: no module of ``imufdi_cli`` imports
``scipy.stats`` on import, and no command reaches it (``tests/cli/test_app.py`` checks
``imufdi detect`` with every detector, ``tests/detectors/test_registry.py`` the import of
every detector class). The one use left is the analysis function
``detectors.jitter.minimum_detectable_step`` (the non-central chi-square, for benchmarks),
which imports it when called.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from imufdi_cli.special import ufunc

#: ``sqrt(2 pi)``, computed as scipy.stats' ``_norm_pdf_C``
_NORM_PDF_C = np.sqrt(2 * np.pi)


def _argsreduce(cond: np.ndarray, *args: np.ndarray) -> list[np.ndarray]:
    """scipy.stats' ``argsreduce``: the elements of each argument where ``cond`` holds, as
    one-dimensional arrays (an argument of size 1 is kept as it is)."""
    new = [np.atleast_1d(a) for a in args]
    if np.all(cond):
        *new, cond = np.broadcast_arrays(*new, cond)
        return [a.ravel() for a in new]
    shape = cond.shape
    return [a if np.size(a) == 1 else np.extract(cond, np.broadcast_to(a, shape)) for a in new]


def _result(output: np.ndarray) -> Any:
    """A NumPy scalar for a zero-dimensional result, else the array (as scipy.stats)."""
    return output[()] if output.ndim == 0 else output


class _Distribution:
    """A continuous distribution with shape parameters all > 0 and support ``[a, b]``,
    evaluated as scipy.stats' ``rv_continuous`` methods evaluate it."""

    #: number of shape parameters
    n_shapes = 0
    #: the support's ends (of the standard form: loc 0, scale 1)
    a = -np.inf
    b = np.inf

    def _parse(
        self, args: tuple[Any, ...], kwds: dict[str, Any]
    ) -> tuple[tuple[np.ndarray, ...], Any, Any]:
        """``(shapes, loc, scale)`` from scipy.stats' arguments: the shape parameters, then
        ``loc`` (default 0) and ``scale`` (default 1), positional or by keyword."""
        n = self.n_shapes
        name = type(self).__name__[1:].lower()
        if not n <= len(args) <= n + 2:
            raise TypeError(f"{name} takes {n} shape parameter(s), loc and scale; got {args}")
        given = dict(zip(("loc", "scale"), args[n:], strict=False))
        for key, value in kwds.items():
            if key not in ("loc", "scale") or key in given:
                raise TypeError(f"{name}: unexpected or repeated argument {key!r}")
            given[key] = value
        shapes = tuple(np.asarray(s) for s in args[:n])
        return shapes, given.get("loc", 0), given.get("scale", 1)

    def _argcheck(self, *shapes: np.ndarray) -> Any:
        cond: Any = 1
        for s in shapes:
            cond = np.logical_and(cond, s > 0)
        return cond

    # the standard-form functions (valid arguments only)
    def _cdf(self, x: np.ndarray, *shapes: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def _sf(self, x: np.ndarray, *shapes: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def _ppf(self, q: np.ndarray, *shapes: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def _isf(self, q: np.ndarray, *shapes: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def _standard(
        self, x: Any, args: tuple[Any, ...], kwds: dict[str, Any]
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...], np.ndarray, np.ndarray]:
        args, loc, scale = self._parse(args, kwds)
        x, loc, scale = map(np.asarray, (x, loc, scale))
        dtype = np.promote_types(x.dtype, np.float64)
        x = np.asarray((x - loc) / scale, dtype=dtype)
        cond0 = self._argcheck(*args) & (scale > 0)
        return x, args, scale, cond0

    def _tail(self, x: Any, args: tuple[Any, ...], kwds: dict[str, Any], upper: bool) -> Any:
        x, args, scale, cond0 = self._standard(x, args, kwds)
        with np.errstate(invalid="ignore"):
            cond1 = (self.a < x) & (x < self.b) & (scale > 0)
        cond2 = cond0 & (x <= self.a) if upper else (x >= np.asarray(self.b)) & cond0
        cond = cond0 & cond1
        output = np.zeros(np.shape(cond), x.dtype)
        np.place(output, (1 - cond0) + np.isnan(x), np.nan)
        np.place(output, cond2, 1.0)
        if np.any(cond):
            good = _argsreduce(cond, x, *args)
            np.place(output, cond, self._sf(*good) if upper else self._cdf(*good))
        return _result(output)

    def cdf(self, x: Any, *args: Any, **kwds: Any) -> Any:
        """``P(X <= x)`` (scipy.stats' ``cdf``)."""
        return self._tail(x, args, kwds, upper=False)

    def sf(self, x: Any, *args: Any, **kwds: Any) -> Any:
        """``P(X > x)`` (scipy.stats' ``sf``)."""
        return self._tail(x, args, kwds, upper=True)

    def _quantile(self, q: Any, args: tuple[Any, ...], kwds: dict[str, Any], upper: bool) -> Any:
        args, loc, scale = self._parse(args, kwds)
        q, loc, scale = map(np.asarray, (q, loc, scale))
        cond0 = self._argcheck(*args) & (scale > 0) & (loc == loc)
        cond1 = (0 < q) & (q < 1)
        cond2 = cond0 & (q == (1 if upper else 0))  # the lower end
        cond3 = cond0 & (q == (0 if upper else 1))  # the upper end
        cond = cond0 & cond1
        output = np.full(np.shape(cond), fill_value=np.nan)
        lower_bound = self.a * scale + loc
        upper_bound = self.b * scale + loc
        np.place(output, cond2, _argsreduce(cond2, lower_bound)[0])
        np.place(output, cond3, _argsreduce(cond3, upper_bound)[0])
        if np.any(cond):
            *good, good_scale, good_loc = _argsreduce(cond, q, *args, scale, loc)
            values = self._isf(*good) if upper else self._ppf(*good)
            np.place(output, cond, values * good_scale + good_loc)
        return _result(output)

    def ppf(self, q: Any, *args: Any, **kwds: Any) -> Any:
        """Quantile ``x`` with ``P(X <= x) = q`` (scipy.stats' ``ppf``)."""
        return self._quantile(q, args, kwds, upper=False)

    def isf(self, q: Any, *args: Any, **kwds: Any) -> Any:
        """Quantile ``x`` with ``P(X > x) = q`` (scipy.stats' ``isf``)."""
        return self._quantile(q, args, kwds, upper=True)


class _Norm(_Distribution):
    """The normal distribution N(loc, scale^2), as ``scipy.stats.norm``.

    ``pdf(x)``, ``cdf(x)``, ``sf(x)``, ``ppf(q)``, ``isf(q)``, each with ``loc=`` and
    ``scale=`` (standard deviation); arrays broadcast, NaN where ``scale <= 0``.
    """

    def pdf(self, x: Any, *args: Any, **kwds: Any) -> Any:
        """Probability density at ``x`` (scipy.stats' ``pdf``)."""
        x, _, scale, cond0 = self._standard(x, args, kwds)
        with np.errstate(invalid="ignore"):
            cond1 = (self.a <= x) & (x <= self.b) & (scale > 0)
        cond = cond0 & cond1
        output = np.zeros(np.shape(cond), x.dtype)
        np.putmask(output, (1 - cond0) + np.isnan(x), np.nan)
        if np.any(cond):
            good_x, good_scale = _argsreduce(cond, x, scale)
            np.place(output, cond, self._pdf(good_x) / good_scale)
        return _result(output)

    @staticmethod
    def _pdf(x: np.ndarray) -> np.ndarray:
        return np.exp(-(x**2) / 2.0) / _NORM_PDF_C

    def _cdf(self, x: np.ndarray, *shapes: np.ndarray) -> np.ndarray:
        return ufunc("ndtr")(x)

    def _sf(self, x: np.ndarray, *shapes: np.ndarray) -> np.ndarray:
        return ufunc("ndtr")(-x)

    def _ppf(self, q: np.ndarray, *shapes: np.ndarray) -> np.ndarray:
        return ufunc("ndtri")(q)

    def _isf(self, q: np.ndarray, *shapes: np.ndarray) -> np.ndarray:
        return -ufunc("ndtri")(q)


class _Chi2(_Distribution):
    """The chi-square distribution with ``df`` degrees of freedom (> 0, need not be an
    integer), as ``scipy.stats.chi2``: ``cdf(x, df)``, ``sf(x, df)``, ``ppf(q, df)``,
    ``isf(q, df)``, with ``loc=`` and ``scale=``; support ``[0, inf)``."""

    n_shapes = 1
    a = 0.0

    def _cdf(self, x: np.ndarray, *shapes: np.ndarray) -> np.ndarray:
        return ufunc("chdtr")(shapes[0], x)

    def _sf(self, x: np.ndarray, *shapes: np.ndarray) -> np.ndarray:
        return ufunc("chdtrc")(shapes[0], x)

    def _ppf(self, q: np.ndarray, *shapes: np.ndarray) -> np.ndarray:
        return 2 * ufunc("gammaincinv")(shapes[0] / 2, q)

    def _isf(self, q: np.ndarray, *shapes: np.ndarray) -> np.ndarray:
        return ufunc("chdtri")(shapes[0], q)


class _F(_Distribution):
    """The F distribution with ``dfn``, ``dfd`` degrees of freedom (> 0), as
    ``scipy.stats.f``: ``cdf(x, dfn, dfd)``, ``sf``, ``ppf(q, dfn, dfd)``, ``isf``, with
    ``loc=`` and ``scale=``; support ``[0, inf)``."""

    n_shapes = 2
    a = 0.0

    def _cdf(self, x: np.ndarray, *shapes: np.ndarray) -> np.ndarray:
        return ufunc("fdtr")(shapes[0], shapes[1], x)

    def _sf(self, x: np.ndarray, *shapes: np.ndarray) -> np.ndarray:
        return ufunc("fdtrc")(shapes[0], shapes[1], x)

    def _ppf(self, q: np.ndarray, *shapes: np.ndarray) -> np.ndarray:
        return ufunc("fdtri")(shapes[0], shapes[1], q)

    def _isf(self, q: np.ndarray, *shapes: np.ndarray) -> np.ndarray:
        # rv_continuous' generic _isf: _ppf(1.0 - q)
        return self._ppf(1.0 - q, *shapes)


class _Gamma(_Distribution):
    """The gamma distribution with shape ``a`` (> 0), as ``scipy.stats.gamma``:
    ``cdf(x, a)``, ``sf``, ``ppf(q, a)``, ``isf``, with ``loc=`` and ``scale=`` (mean
    ``a * scale``); support ``[0, inf)``."""

    n_shapes = 1
    a = 0.0

    def _cdf(self, x: np.ndarray, *shapes: np.ndarray) -> np.ndarray:
        return ufunc("gammainc")(shapes[0], x)

    def _sf(self, x: np.ndarray, *shapes: np.ndarray) -> np.ndarray:
        return ufunc("gammaincc")(shapes[0], x)

    def _ppf(self, q: np.ndarray, *shapes: np.ndarray) -> np.ndarray:
        return ufunc("gammaincinv")(shapes[0], q)

    def _isf(self, q: np.ndarray, *shapes: np.ndarray) -> np.ndarray:
        return ufunc("gammainccinv")(shapes[0], q)


#: ``scipy.stats.norm``'s pdf, cdf, sf, ppf, isf: the same floats
norm = _Norm()
#: ``scipy.stats.chi2``'s cdf, sf, ppf, isf: the same floats
chi2 = _Chi2()
#: ``scipy.stats.f``'s cdf, sf, ppf, isf: the same floats
f = _F()
#: ``scipy.stats.gamma``'s cdf, sf, ppf, isf: the same floats
gamma = _Gamma()

__all__ = ["chi2", "f", "gamma", "norm"]
