"""numpy's LAPACK gufuncs called directly: the same floats as ``numpy.linalg``, without its
wrappers' Python overhead.

The episode fits call ``svd``, ``solve`` and ``det`` on small matrices (a window of about
200 samples by four or five columns, 1x1 and 2x2 normal equations) three or four times an
episode, thousands of episodes an hour; ``numpy.linalg``'s wrappers (array conversion, type
checks, an ``errstate`` with a callback) cost as much as LAPACK itself there. These
functions call the gufunc ``numpy.linalg`` calls, with the same signature, on the same
array, so the results are the same to the bit (tests/episodes/test_lapack.py compares them
with ``numpy.linalg``'s). What ``numpy.linalg`` raises on a failure (``LinAlgError``: a
singular matrix, an SVD that does not converge; numpy signals it through the invalid
floating-point flag) comes from ``numpy.linalg`` itself: on that flag the call is repeated
through it. Inputs must be float64 arrays of the shapes given (what the fits pass); without
numpy's private ``_umath_linalg`` module the public functions are used.
"""

from __future__ import annotations

from typing import Any

import numpy as np

_gufuncs: Any
try:  # numpy >= 2: numpy.linalg._umath_linalg; 1.x: numpy.linalg._umath_linalg too
    from numpy.linalg import _umath_linalg as _gufuncs
except ImportError:  # pragma: no cover - numpy without the private module
    _gufuncs = None

_SVD_S = getattr(_gufuncs, "svd_s", None)
_SOLVE = getattr(_gufuncs, "solve", None)
_DET = getattr(_gufuncs, "det", None)


def svd_reduced(a: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``numpy.linalg.svd(a, full_matrices=False)``.

    Parameters
    ----------
    a : ndarray, shape (m, k), float64

    Returns
    -------
    u : ndarray, shape (m, min(m, k))
    s : ndarray, shape (min(m, k),)
    vt : ndarray, shape (min(m, k), k)
    """
    if _SVD_S is None:  # pragma: no cover
        u, s, vt = np.linalg.svd(a, full_matrices=False)
        return u, s, vt
    try:
        with np.errstate(invalid="raise", over="ignore", divide="ignore", under="ignore"):
            u, s, vt = _SVD_S(a, signature="d->ddd")
    except FloatingPointError:  # numpy's own call raises what numpy raises (no convergence)
        u, s, vt = np.linalg.svd(a, full_matrices=False)
    return u, s, vt


def solve(a: np.ndarray, b: np.ndarray) -> Any:
    """``numpy.linalg.solve(a, b)`` for a square ``a`` (p, p) and ``b`` (p, n), float64."""
    if _SOLVE is None:  # pragma: no cover
        return np.linalg.solve(a, b)
    try:
        with np.errstate(invalid="raise", over="ignore", divide="ignore", under="ignore"):
            return _SOLVE(a, b, signature="dd->d")
    except FloatingPointError:  # numpy's own call raises what numpy raises (singular)
        return np.linalg.solve(a, b)


def det(a: np.ndarray) -> float:
    """``float(numpy.linalg.det(a))`` of a square float64 ``a`` (numpy calls the gufunc
    without an ``errstate``)."""
    if _DET is None:  # pragma: no cover
        return float(np.linalg.det(a))
    return float(_DET(a, signature="d->d"))
