"""Non-negative least squares without importing ``scipy.optimize``.

``scipy.optimize`` costs about 0.3 s of CPU to import on the build machine, more than
:func:`~imufdi_cli.detectors.parity.residual_sigma` (every calibration of glt, bank and the
episode builders) spends on its one small NNLS, and more than a quarter of what ``imufdi
info`` spends reading a 10-minute log. Its ``nnls`` is a thin Python wrapper
(scipy 1.17 ``optimize/_nnls.py``) around the compiled Lawson-Hanson routine of the
extension module ``scipy.optimize._slsqplib``, which needs nothing else of the package.

:func:`nnls` loads that extension module alone and applies the wrapper's own checks, so it
runs the same compiled code on the same arguments: the same floats
(``tests/test_nnls.py`` compares them bit for bit). It does so only when the installed
wrapper is the one this mirrors (its source calls ``_nnls(A, b, maxiter)`` imported from
``._slsqplib``); otherwise, or when the module cannot be loaded, it calls
``scipy.optimize.nnls`` itself.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from imufdi_cli.special import extension

_MODULE = "scipy.optimize._slsqplib"
#: the lines of scipy's wrapper that this module mirrors
_WRAPPER_LINES = ("from ._slsqplib import nnls as _nnls", "x, rnorm, info = _nnls(A, b, maxiter)")


@functools.lru_cache(maxsize=1)
def _compiled() -> Callable[..., Any] | None:
    """The compiled routine, or None when scipy's wrapper is not the one mirrored here."""
    try:
        import scipy

        source = (Path(scipy.__file__).parent / "optimize" / "_nnls.py").read_text(encoding="utf-8")
    except (ImportError, OSError):
        return None
    if not all(line in source for line in _WRAPPER_LINES):
        return None
    # the extension module alone, as imufdi_cli.special loads scipy.special's (the package,
    # if imported later, finds it: one module object, not two)
    routine = getattr(extension(_MODULE), "nnls", None)
    return routine if callable(routine) else None


def nnls(A: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, float]:
    """``argmin_x ||A x - b||_2`` subject to ``x >= 0`` (Lawson & Hanson 1995, ch. 23).

    The same floats as ``scipy.optimize.nnls(A, b)`` (default ``maxiter = 3 n``).

    Parameters
    ----------
    A : array_like, shape (m, n)
    b : array_like, shape (m,) or (m, 1)

    Returns
    -------
    x : ndarray, shape (n,)
    rnorm : float
        ``||A x - b||_2``.

    Raises
    ------
    ValueError
        Non-finite or mis-shaped arguments (as scipy).
    RuntimeError
        The iteration limit was reached (as scipy).
    """
    routine = _compiled()
    if routine is None:
        from scipy.optimize import nnls as scipy_nnls

        column = np.asarray(b)
        if column.ndim == 2 and column.shape[1] == 1:  # scipy < 1.17 takes only a 1-D b
            b = column[:, 0]
        x, rnorm = scipy_nnls(A, b)
        return x, float(rnorm)
    # scipy 1.17 optimize/_nnls.py, checks and defaults as there
    A = np.asarray_chkfinite(A, dtype=np.float64, order="C")
    b = np.asarray_chkfinite(b, dtype=np.float64)
    if len(A.shape) != 2:
        raise ValueError(f"Expected a 2D array, but the shape of A is {A.shape}")
    if (b.ndim > 2) or ((b.ndim == 2) and (b.shape[1] != 1)):
        raise ValueError(f"Expected a 1D array (or 2D with one column), but b has shape {b.shape}")
    if b.ndim == 2:
        b = b.ravel()
    m, n = A.shape
    if m != b.shape[0]:
        raise ValueError(
            f"Incompatible dimensions. The first dimension of A is {m}, while the shape of b"
            f" is {(b.shape[0],)}"
        )
    x, rnorm, info = routine(A, b, 3 * n)
    if info == 3:
        raise RuntimeError("Maximum number of iterations reached.")
    return x, float(rnorm)
