"""Suite-wide settings and hooks (docs/testing.md: suite time)."""

from __future__ import annotations

import gc
import os

import pytest

# One BLAS thread per test process, as the `imufdi` command runs (imufdi_cli.cli): the suite
# runs two xdist workers on two cores, and numpy's and scipy's OpenBLAS would each add a
# thread per core to every worker; on thin matrices those threads only spin against the
# other worker (tests/detectors 41-46 -> 32-35 s of CPU, pca-parity's 45-dimension
# eigenvalue test 3-4 -> 0.3 s). Set here, when pytest loads this file and before any test
# module imports numpy; xdist workers inherit it from the controller. A value set by the
# user is kept. The outputs are those of the command (and of the split-identical records,
# made with one thread).
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")


@pytest.hookimpl(trylast=True)
def pytest_collection_finish(session: pytest.Session) -> None:
    """Move what collection left alive (imported modules, collected items: about 200 000
    objects) out of the garbage collector's sight: they live to the end of the session, so
    every full collection would walk them again for nothing, as would the five collections
    pytest runs at the end of a session to report unraisable exceptions. Objects made by
    the tests are collected as before."""
    gc.freeze()
