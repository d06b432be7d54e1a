"""imufdi_cli.maths.parity.nonnegative_least_squares against scipy.optimize.nnls.

scipy.optimize.nnls is the independent oracle. When the unconstrained least-squares
solution is non-negative both return the same minimiser, computed by different
factorisations (LAPACK's SVD-based ``gelsd`` here, Lawson & Hanson's Householder QR
there), so they agree to rounding amplified by the condition number of A: the tolerance is
``1e3 * eps * cond(A)`` relative to ``|x|`` (a backward-stable solver's forward error is a
small multiple of ``eps * cond``; the 1e3 covers that multiple for these sizes, and a wrong
solution is off by far more). When a constraint is active the function hands the problem
to scipy's solver, so the results are equal.
"""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from imufdi_cli.maths.parity import (
    nonnegative_least_squares,
    residual_projector,
    residual_sigma,
    residuals,
)

EPS = float(np.finfo(np.float64).eps)


def _tolerance(A: np.ndarray) -> float:
    return 1e3 * EPS * float(np.linalg.cond(A))  # module docstring


@pytest.mark.parametrize("seed", range(20))
def test_an_interior_minimum_is_scipys(seed: int) -> None:
    from scipy.optimize import nnls

    rng = np.random.default_rng(seed)
    m = int(rng.integers(3, 20))
    n = int(rng.integers(1, m + 1))
    A = rng.normal(size=(m, n))
    truth = rng.uniform(0.1, 2.0, size=n)
    b = A @ truth + 0.01 * rng.normal(size=m)
    x = nonnegative_least_squares(A, b)
    expected, _ = nnls(A, b)
    assert np.all(x >= 0)
    assert_allclose(x, expected, rtol=0, atol=_tolerance(A) * float(np.linalg.norm(expected)))


@pytest.mark.parametrize("seed", range(20))
def test_active_constraints_give_scipys_solution(seed: int) -> None:
    from scipy.optimize import nnls

    rng = np.random.default_rng(100 + seed)
    m = int(rng.integers(3, 20))
    n = int(rng.integers(2, m + 1))
    A = rng.normal(size=(m, n))
    truth = rng.normal(size=n)
    truth[0] = -1.0  # at least one component the unconstrained fit makes negative
    b = A @ truth
    assert np.any(np.linalg.lstsq(A, b, rcond=None)[0] < 0)
    x = nonnegative_least_squares(A, b)
    expected, _ = nnls(A, b)
    assert_array_equal(x, expected)
    assert np.all(x >= 0)


def test_the_noise_calibration_matches_scipys_nnls() -> None:
    """``residual_sigma`` of a 16-IMU array, against the same maths with scipy's nnls."""
    from scipy.optimize import nnls

    rng = np.random.default_rng(7)
    H = np.linalg.qr(rng.normal(size=(16, 3)))[0] * 3.0
    sigma = rng.uniform(0.5, 1.5, size=16) * 1e-3
    measurements = rng.normal(size=(4000, 3)) @ H.T + rng.normal(size=(4000, 16)) * sigma
    got = residual_sigma(H, measurements, outlier_cut=None)
    r = residuals(H, measurements)
    mixing = residual_projector(H) ** 2
    expected, _ = nnls(mixing, r.var(axis=0, ddof=1))
    assert_allclose(got, np.sqrt(expected), rtol=_tolerance(mixing))


def test_a_white_noise_calibration_does_not_import_scipy_optimize(fresh_python) -> None:
    probe = (
        "import sys\n"
        "import numpy as np\n"
        "from imufdi_cli.maths.parity import residual_sigma\n"
        "rng = np.random.default_rng(1)\n"
        "H = np.linalg.qr(rng.normal(size=(8, 3)))[0]\n"
        "m = rng.normal(size=(500, 3)) @ H.T + 1e-3 * rng.normal(size=(500, 8))\n"
        "residual_sigma(H, m)\n"
        "print('scipy.optimize' in sys.modules)\n"
    )
    done = fresh_python(probe)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "False"
