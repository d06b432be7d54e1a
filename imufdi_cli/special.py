"""scipy.special's inverse distribution functions without importing ``scipy.special``.

``import scipy.special`` costs about 0.3 s of CPU on the build machine, most of
it ``scipy._lib.array_api_compat`` cloning numpy, which imports ``numpy.f2py`` and
``numpy.testing``: more than a tenth of what ``imufdi info`` spends reading a 1-hour log,
paid by every ``imufdi detect -d glt`` for a few quantiles (glt's thresholds, the episode
intervals). The functions themselves are ufuncs of the compiled extension module
``scipy.special._ufuncs``, which needs none of that.

:func:`ufunc` loads that extension module with the package's ``__init__`` left out (a bare
package module stands in for ``scipy.special`` while the extension initialises, then is
removed), so the ufuncs are the very objects ``scipy.special`` exports: the same compiled
code, the same floats (``tests/test_special.py`` checks both). If ``scipy.special`` is
already imported, or the extension cannot be loaded that way, the package's own ufunc is
used. A later ``import scipy.special`` runs the package normally and finds the extension
already loaded (one module object, not two).

:func:`extension` does the same for any compiled module of a scipy subpackage;
:func:`lfilter` uses it for ``scipy.signal.lfilter``'s compiled filter: ``import
scipy.signal`` costs about 1.5 s of CPU (it imports ``scipy.stats``), paid by every ``imufdi
detect -d bank`` for two first-order filters. :func:`brentq` uses it for
``scipy.optimize.brentq``'s compiled root finder: ``import scipy.optimize`` costs about
0.5 s of CPU, paid by every ``imufdi calibrate`` for the jitter fit's one root.
"""

from __future__ import annotations

import functools
import operator
import sys
import threading
import types
from pathlib import Path
from typing import Any

import numpy as np

_PACKAGE = "scipy.special"
_MODULE = "scipy.special._ufuncs"
_LOCK = threading.Lock()


@functools.cache
def extension(module: str) -> Any:
    """The compiled extension module ``module`` of a scipy subpackage (e.g.
    ``"scipy.special._ufuncs"``, ``"scipy.signal._sigtools"``,
    ``"scipy.fft._pocketfft.pypocketfft"``) loaded without running the
    subpackage's ``__init__`` (None when that fails; the module itself when it or its
    package is already imported: the package is then used as it is).

    Parameters
    ----------
    module : str
        ``scipy.<subpackage>.<extension>``.

    Returns
    -------
    module or None
    """
    package = module.rpartition(".")[0]
    with _LOCK:
        loaded = sys.modules.get(module)
        if loaded is not None or package in sys.modules:
            return loaded
        try:
            import importlib

            import scipy

            attribute = package.split(".")[1]
            stub = types.ModuleType(package)
            stub.__path__ = [str(Path(scipy.__file__).parent.joinpath(*package.split(".")[1:]))]
            stub.__package__ = package
            sys.modules[package] = stub
            try:
                return importlib.import_module(module)
            finally:
                # the real package is imported normally if anything asks for it later
                if sys.modules.get(package) is stub:
                    del sys.modules[package]
                if vars(scipy).get(attribute) is stub:  # (getattr would import it)
                    delattr(scipy, attribute)
        except Exception:  # any failure: the package's own functions (the callers')
            # (extension modules loaded before the failure stay: the package reuses them)
            return None


def ufunc(name: str) -> Any:
    """The ufunc ``scipy.special.<name>`` (e.g. ``"gammaincinv"``, ``"fdtri"``,
    ``"chdtri"``, ``"stdtrit"``), loaded without importing ``scipy.special`` when it is
    not imported already.

    Parameters
    ----------
    name : str
        A function of ``scipy.special._ufuncs``.

    Returns
    -------
    numpy.ufunc
        The same object ``scipy.special`` exports under that name.
    """
    if _PACKAGE not in sys.modules:
        found = getattr(extension(_MODULE), name, None)
        if found is not None:
            return found
    import scipy.special

    return getattr(scipy.special, name)


def lfilter(b: Any, a: Any, x: Any, axis: int = -1, zi: Any = None) -> Any:
    """``scipy.signal.lfilter(b, a, x, axis, zi)`` for a recursive filter (``len(a) > 1``),
    without importing ``scipy.signal`` (about 1.5 s of CPU: it imports ``scipy.stats``).

    scipy's wrapper (scipy 1.17 ``signal/_signaltools.py``) passes such a filter straight
    to the compiled direct-form II transposed filter ``_sigtools._linear_filter`` after
    ``np.atleast_1d`` of the coefficients and ``np.asarray`` of the data; so does this
    function, so the outputs are the same floats. A moving-average filter (``len(a) ==
    1``), or a scipy whose extension cannot be loaded alone, goes through
    ``scipy.signal.lfilter`` itself.

    Parameters
    ----------
    b, a : array_like, shapes (M,) and (N,)
        Numerator and denominator coefficients (``a[0] != 0``).
    x : array_like
        Data, filtered along ``axis``.
    axis : int
        Axis of ``x`` along which the filter runs.
    zi : array_like, optional
        Initial state, ``x``'s shape with ``max(M, N) - 1`` along ``axis``.

    Returns
    -------
    ndarray, or (ndarray, ndarray)
        The filtered data (``x``'s shape), and the final state when ``zi`` is given.
    """
    b, a = np.atleast_1d(b), np.atleast_1d(a)
    sigtools = extension("scipy.signal._sigtools")
    usable = b.ndim == 1 and b.size > 0 and a.ndim == 1 and a.size > 1
    if sigtools is None or not usable:
        from scipy import signal

        return signal.lfilter(b, a, x, axis=axis, zi=zi)
    x = np.asarray(x)
    if zi is None:
        return sigtools._linear_filter(b, a, x, axis)
    out, zf = sigtools._linear_filter(b, a, x, axis, np.asarray(zi))
    return out, zf


def fft(x: np.ndarray, forward: bool = True) -> np.ndarray:
    """``scipy.fft.fft(x, axis=-1)`` (``forward``) or ``scipy.fft.ifft(x, axis=-1)``
    without importing ``scipy.fft`` (about 0.4 s of CPU, most of it scipy's array-API
    layer).

    For a float64 or complex128 array, aligned and in native byte order, scipy's wrapper
    (scipy 1.17 ``fft/_pocketfft/basic.py``: ``c2c``) passes it uncopied to the compiled
    ``pypocketfft.c2c(x, (axis,), forward, norm, None, workers)`` with norm 0 forward and
    2 backward (1/n) and one worker; so does this function, so the outputs are the same
    floats. Anything else (or a scipy whose extension cannot be loaded alone) goes through
    ``scipy.fft`` itself.

    Parameters
    ----------
    x : ndarray, shape (..., n)
        Samples (n >= 1), transformed along the last axis.
    forward : bool
        The forward transform (``fft``) or the inverse (``ifft``, scaled by 1/n).

    Returns
    -------
    ndarray, complex, shape (..., n)
    """
    pocketfft = extension("scipy.fft._pocketfft.pypocketfft")
    plain = (
        isinstance(x, np.ndarray)
        and x.dtype in (np.float64, np.complex128)
        and x.dtype.isnative
        and x.flags.aligned
        and x.ndim >= 1
        and x.shape[-1] >= 1
    )
    if pocketfft is None or not plain:
        from scipy import fft as scipy_fft

        return scipy_fft.fft(x, axis=-1) if forward else scipy_fft.ifft(x, axis=-1)
    return pocketfft.c2c(x, (x.ndim - 1,), forward, 0 if forward else 2, None, 1)


#: scipy.optimize.brentq's defaults (scipy 1.17 ``optimize/_zeros_py.py``)
BRENTQ_XTOL = 2e-12
BRENTQ_RTOL = 4 * float(np.finfo(float).eps)
BRENTQ_MAXITER = 100


def brentq(
    f: Any,
    a: float,
    b: float,
    xtol: float = BRENTQ_XTOL,
    rtol: float = BRENTQ_RTOL,
    maxiter: int = BRENTQ_MAXITER,
) -> float:
    """``scipy.optimize.brentq(f, a, b, xtol=xtol, rtol=rtol, maxiter=maxiter)`` without
    importing ``scipy.optimize`` (about 0.5 s of CPU).

    scipy's wrapper (scipy 1.17 ``optimize/_zeros_py.py``) checks ``xtol > 0`` and ``rtol
    >= 4 eps``, wraps ``f`` so that a NaN value raises ValueError, and calls the compiled
    Brent solver ``_zeros._brentq(f, a, b, xtol, rtol, maxiter, (), False, True)``; so does
    this function, so the root is the same float. A scipy whose extension cannot be loaded
    alone goes through ``scipy.optimize.brentq`` itself.

    Parameters
    ----------
    f : callable float -> float
        Continuous on [a, b], ``f(a)`` and ``f(b)`` of opposite signs.
    a, b : float
        The bracket.
    xtol, rtol : float
        The root is within ``xtol + rtol * |root|`` of a true root (``xtol > 0``,
        ``rtol >= 4 eps``).
    maxiter : int
        Iterations before RuntimeError ("failed to converge").

    Returns
    -------
    float

    Raises
    ------
    ValueError
        A bad tolerance, ``f(a)`` and ``f(b)`` of the same sign, or a NaN value of ``f``.
    RuntimeError
        No convergence in ``maxiter`` iterations.
    """
    zeros = extension("scipy.optimize._zeros")
    if zeros is None:
        from scipy import optimize

        return float(optimize.brentq(f, a, b, xtol=xtol, rtol=rtol, maxiter=maxiter))
    maxiter = operator.index(maxiter)
    if xtol <= 0:
        raise ValueError(f"xtol too small ({xtol:g} <= 0)")
    if rtol < BRENTQ_RTOL:
        raise ValueError(f"rtol too small ({rtol:g} < {BRENTQ_RTOL:g})")

    def checked(x: float) -> Any:
        value = f(x)
        if np.isnan(value):
            raise ValueError(f"The function value at x={x} is NaN; solver cannot continue.")
        return value

    return float(zeros._brentq(checked, a, b, xtol, rtol, maxiter, (), False, True))
