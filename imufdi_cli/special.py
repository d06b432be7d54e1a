"""scipy.special's inverse distribution functions without importing ``scipy.special``.

``import scipy.special`` costs about 0.3 s of CPU on the build machine (issue 20), most of
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
"""

from __future__ import annotations

import functools
import sys
import threading
import types
from pathlib import Path
from typing import Any

_PACKAGE = "scipy.special"
_MODULE = "scipy.special._ufuncs"
_LOCK = threading.Lock()


@functools.lru_cache(maxsize=1)
def _extension() -> Any:
    """``scipy.special._ufuncs`` loaded without the package (None when that fails)."""
    with _LOCK:
        loaded = sys.modules.get(_MODULE)
        if loaded is not None or _PACKAGE in sys.modules:
            return loaded
        try:
            import importlib

            import scipy

            stub = types.ModuleType(_PACKAGE)
            stub.__path__ = [str(Path(scipy.__file__).parent / "special")]
            stub.__package__ = _PACKAGE
            sys.modules[_PACKAGE] = stub
            try:
                return importlib.import_module(_MODULE)
            finally:
                # the real package is imported normally if anything asks for it later
                if sys.modules.get(_PACKAGE) is stub:
                    del sys.modules[_PACKAGE]
                if vars(scipy).get("special") is stub:  # (getattr would import it)
                    delattr(scipy, "special")
        except Exception:  # any failure: the package's own functions (ufunc below)
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
        found = getattr(_extension(), name, None)
        if found is not None:
            return found
    import scipy.special

    return getattr(scipy.special, name)
