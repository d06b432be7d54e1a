"""imufdi_cli.nnls gives the same floats as scipy.optimize.nnls, without importing it."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from imufdi_cli import nnls as module
from imufdi_cli.nnls import nnls


def _problems() -> list[tuple[np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(20261123)
    out = []
    for m, n in [(1, 1), (3, 2), (16, 16), (48, 48), (30, 5), (5, 30)]:
        for _ in range(5):
            out.append((rng.normal(size=(m, n)), rng.normal(size=m)))
    # the shape residual_sigma solves: squared hat-matrix complement, residual variances
    H = rng.normal(size=(16, 3))
    mixing = (np.eye(16) - H @ np.linalg.pinv(H)) ** 2
    out.append((mixing, mixing @ rng.uniform(0.5, 2.0, 16)))
    out.append((mixing, rng.uniform(-1.0, 1.0, 16)))  # some constraints active
    out.append((np.zeros((4, 3)), np.ones(4)))
    return out


@pytest.mark.parametrize("index", range(len(_problems())))
def test_same_floats_as_scipy(index: int, scipy_optimize) -> None:
    A, b = _problems()[index]
    x, rnorm = nnls(A, b)
    x_ref, rnorm_ref = scipy_optimize.nnls(A, b)
    assert np.array_equal(x, x_ref)
    assert rnorm == rnorm_ref
    assert np.all(x >= 0)


#: the scipy release whose ``optimize/_nnls.py`` imufdi_cli.nnls mirrors; older releases
#: (another wrapper) get scipy's own nnls, checked by the tests above and below
MIRRORED_SCIPY = (1, 17)


def _fast_path_expected() -> bool:
    import scipy

    return tuple(int(part) for part in scipy.__version__.split(".")[:2]) >= MIRRORED_SCIPY


def test_the_compiled_routine_is_the_one_used() -> None:
    # with scipy 1.17 the wrapper is mirrored; if it changes, nnls falls back to scipy's
    # own (still correct) and this says the fast path is gone
    if not _fast_path_expected():
        assert module._compiled() is None  # an older wrapper: scipy's own nnls is used
        pytest.skip("scipy older than 1.17: its nnls wrapper is not the one mirrored")
    assert module._compiled() is not None


def test_column_b_and_bad_arguments_as_scipy(scipy_optimize) -> None:
    A, b = _problems()[12]  # 16 x 16
    # a one-column b is b (scipy 1.17 takes it too; older releases only the 1-D b)
    assert np.array_equal(nnls(A, b[:, None])[0], scipy_optimize.nnls(A, b)[0])
    for bad_A, bad_b in [(A, b[:-1]), (A[0], b), (A, np.ones((b.size, 2)))]:
        with pytest.raises(ValueError):
            nnls(bad_A, bad_b)
    with pytest.raises(ValueError):
        nnls(np.where(A > 0, np.nan, A), b)
    with pytest.raises(ValueError):
        scipy_optimize.nnls(np.where(A > 0, np.nan, A), b)


def test_fallback_when_the_wrapper_differs(monkeypatch: pytest.MonkeyPatch, scipy_optimize) -> None:
    A, b = _problems()[0]
    monkeypatch.setattr(module, "_compiled", lambda: None)
    x, rnorm = nnls(A, b)
    assert rnorm == scipy_optimize.nnls(A, b)[1]
    assert np.array_equal(x, scipy_optimize.nnls(A, b)[0])
    # the one-column b of the docstring, whatever the release's wrapper takes
    assert np.array_equal(nnls(A, b[:, None])[0], x)


def test_using_it_does_not_import_scipy_optimize() -> None:
    if not _fast_path_expected():
        pytest.skip("scipy older than 1.17: nnls calls scipy.optimize.nnls")
    code = (
        "import sys, numpy as np; from imufdi_cli.nnls import nnls;"
        "nnls(np.eye(3), np.ones(3));"
        "print(sorted(m for m in sys.modules if m.startswith('scipy.optimize')))"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "['scipy.optimize._slsqplib']"
