"""imufdi_cli.special: scipy.special's own ufuncs, loaded without importing scipy.special."""

from __future__ import annotations

import hashlib
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from imufdi_cli.special import ufunc

NAMES = ("gammaincinv", "fdtri", "chdtri", "stdtrit")

# In a fresh interpreter: the ufuncs load without the package, give what the package's give
# (checked after importing it: the same objects, so the same floats), and the package imports
# normally afterwards.
CHILD = textwrap.dedent(
    """
    import sys
    import numpy as np
    import scipy
    from imufdi_cli.special import ufunc
    names = {names!r}
    loaded = {{name: ufunc(name) for name in names}}
    rng = np.random.default_rng(17200)
    q = rng.uniform(0.0, 1.0, 200)
    df = rng.uniform(0.5, 60.0, 200)
    first = [
        loaded["gammaincinv"](df, q),
        loaded["fdtri"](df, df[::-1], q),
        loaded["chdtri"](df, q),
        loaded["stdtrit"](df, q),
    ]
    print("special" in vars(scipy), "scipy.special" in sys.modules)
    import scipy.special as package
    print(all(getattr(package, name) is loaded[name] for name in names))
    second = [
        package.gammaincinv(df, q),
        package.fdtri(df, df[::-1], q),
        package.chdtri(df, q),
        package.stdtrit(df, q),
    ]
    print(all(a.tobytes() == b.tobytes() for a, b in zip(first, second)))
    print(package.gamma(5.0) == 24.0)
    from imufdi_cli.quantiles import chi2
    print(chi2.ppf(0.99, 1) == 2 * package.gammaincinv(0.5, 0.99))
    from imufdi_cli.special import lfilter
    filtered, state = lfilter([0.25], [1.0, -0.75], np.outer(q, df), axis=1, zi=np.ones((200, 1)))
    import hashlib
    print(hashlib.sha256(filtered.tobytes() + state.tobytes()).hexdigest())
    from imufdi_cli.special import fft
    spectrum = fft(np.outer(q, df))
    print(hashlib.sha256(spectrum.tobytes() + fft(spectrum, False).tobytes()).hexdigest())
    print("scipy.signal" in sys.modules, "scipy.stats" in sys.modules, "scipy.fft" in sys.modules)
    from imufdi_cli.special import brentq
    print(repr(brentq(lambda x: x**3 - 2.0 * x - 5.0, 2.0, 3.0)), "scipy.optimize" in sys.modules)
    """
)


def test_loads_without_the_package_and_gives_its_ufuncs(scipy_stats, scipy_optimize) -> None:
    done = subprocess.run(
        [sys.executable, "-c", CHILD.format(names=NAMES)],
        capture_output=True,
        text=True,
        check=True,
    )
    *first, digest, fft_digest, signal_loaded, stats_loaded, fft_loaded, root, optimize_loaded = (
        done.stdout.split()
    )
    assert first == ["False", "False", "True", "True", "True", "True"]
    assert (signal_loaded, stats_loaded, fft_loaded, optimize_loaded) == ("False",) * 4
    # Brent's root without scipy.optimize is the root scipy.optimize.brentq finds
    assert float(root) == scipy_optimize.brentq(lambda x: x**3 - 2.0 * x - 5.0, 2.0, 3.0)
    # the same bits as scipy.signal.lfilter (in this process: scipy.signal imports
    # scipy.stats, hence the fixture, which puts the test on the worker that imports it)
    from scipy import signal

    rng = np.random.default_rng(17200)
    q, df = rng.uniform(0.0, 1.0, 200), rng.uniform(0.5, 60.0, 200)
    want = signal.lfilter([0.25], [1.0, -0.75], np.outer(q, df), axis=1, zi=np.ones((200, 1)))
    assert digest == hashlib.sha256(want[0].tobytes() + want[1].tobytes()).hexdigest()
    from scipy import fft

    spectrum = fft.fft(np.outer(q, df), axis=-1)
    inverse = fft.ifft(spectrum, axis=-1)
    assert fft_digest == hashlib.sha256(spectrum.tobytes() + inverse.tobytes()).hexdigest()


def test_quantiles_do_not_import_the_package(quantiles_scipy_modules) -> None:
    # one fresh process with test_quantiles.py's scipy.stats check (tests/conftest.py)
    assert "scipy.special" not in quantiles_scipy_modules


def test_lfilter_is_scipy_signal_lfilter_to_the_bit(scipy_stats) -> None:
    """Recursive filters of several orders, axes and initial states (the extension's
    path), a moving-average filter and 1-D data (scipy.signal's own path), bit for bit."""
    from scipy import signal

    from imufdi_cli.special import lfilter

    rng = np.random.default_rng(17201)
    x = rng.normal(size=(7, 60, 3))
    cases = [
        ([0.1], [1.0, -0.9], 1, np.zeros((7, 1, 3))),
        ([0.3, 0.2], [1.0, -0.5, 0.1], 0, rng.normal(size=(2, 60, 3))),
        ([1.0], [2.0, -0.4], -1, None),
        ([0.5, 0.5], [1.0], 1, None),
    ]
    for b, a, axis, zi in cases:
        got = lfilter(b, a, x, axis=axis, zi=zi)
        want = signal.lfilter(b, a, x, axis=axis, zi=zi)
        got, want = (got, want) if zi is not None else ((got,), (want,))
        assert all(g.tobytes() == w.tobytes() and g.shape == w.shape for g, w in zip(got, want))
    one = rng.normal(size=50)
    assert (
        lfilter([0.2], [1.0, -0.8], one).tobytes()
        == signal.lfilter([0.2], [1.0, -0.8], one).tobytes()
    )


def test_fft_is_scipy_fft_to_the_bit(scipy_fft) -> None:
    """Real and complex, odd and even lengths, a batch, and what goes through scipy.fft
    itself (float32, a non-native byte order)."""
    from imufdi_cli.special import fft

    rng = np.random.default_rng(17203)
    arrays = [rng.standard_normal(shape) for shape in [(1,), (6,), (7,), (4, 3, 250)]]
    arrays += [arrays[-1] + 1j * rng.standard_normal((4, 3, 250))]
    arrays += [arrays[2].astype(np.float32), arrays[2].astype(">f8")]
    for x in arrays:
        assert fft(x).tobytes() == scipy_fft.fft(x, axis=-1).tobytes(), x.shape
        assert fft(x, False).tobytes() == scipy_fft.ifft(x, axis=-1).tobytes(), x.shape


def test_brentq_is_scipy_optimize_brentq_to_the_bit(scipy_optimize) -> None:
    """Smooth roots, a flat one, a step (the empirical rate the jitter fit solves), the
    tolerances and iteration limits given, and scipy's errors for the same bad input."""
    from imufdi_cli.special import brentq

    rng = np.random.default_rng(17860)
    levels = np.sort(rng.uniform(0.0, 1.0, 500))
    cases = [
        (lambda x: x**3 - 2.0 * x - 5.0, 2.0, 3.0, {}),
        (np.cos, 0.0, 3.0, {"xtol": 1e-3}),
        (lambda x: (x - 0.3) ** 5, -1.0, 2.0, {}),
        (lambda x: float(np.mean(levels < x)) - 0.37, 0.0, 1.0, {"xtol": 1e-9}),
        (lambda x: np.exp(x) - 1e6, 0.0, 100.0, {"rtol": 1e-10, "maxiter": 500}),
        (lambda x: x - 1.0, 1.0, 5.0, {}),  # a root at the bracket's end
    ]
    for f, a, b, options in cases:
        assert brentq(f, a, b, **options) == scipy_optimize.brentq(f, a, b, **options)
    bad = [
        (lambda x: x * x + 1.0, -1.0, 1.0, {}),  # no sign change
        (lambda x: np.nan, 0.0, 1.0, {}),
        (np.cos, 0.0, 3.0, {"xtol": 0.0}),
        (np.cos, 0.0, 3.0, {"rtol": 1e-20}),
    ]
    for f, a, b, options in bad:
        for solver in (brentq, scipy_optimize.brentq):
            with pytest.raises(ValueError):
                solver(f, a, b, **options)
    for solver in (brentq, scipy_optimize.brentq):
        with pytest.raises(RuntimeError, match="converge"):
            solver(lambda x: np.exp(x) - 1e6, 0.0, 100.0, maxiter=3)


def test_brentq_without_the_extension_is_scipy_optimize_brentq(
    monkeypatch: pytest.MonkeyPatch, scipy_optimize
) -> None:
    from imufdi_cli import special

    monkeypatch.setattr(special, "extension", lambda module: None)
    f = lambda x: x**3 - 2.0 * x - 5.0  # noqa: E731
    assert special.brentq(f, 2.0, 3.0, xtol=1e-6) == scipy_optimize.brentq(f, 2.0, 3.0, xtol=1e-6)


def test_with_the_package_imported_its_own_functions_are_returned(scipy_special) -> None:
    for name in NAMES:
        assert ufunc(name) is getattr(scipy_special, name)
    assert np.array_equal(
        ufunc("fdtri")(1.0, 10.0, [0.5, 0.99]), scipy_special.fdtri(1, 10, [0.5, 0.99])
    )


def test_when_the_extension_cannot_be_loaded_alone_the_package_is_used() -> None:
    code = textwrap.dedent(
        """
        import importlib, sys
        real = importlib.import_module

        def refuse(name, *args, **kwargs):
            if name == "scipy.special._ufuncs":
                raise ImportError("refused for the test")
            return real(name, *args, **kwargs)

        importlib.import_module = refuse
        from imufdi_cli.special import ufunc
        f = ufunc("fdtri")
        importlib.import_module = real
        import scipy.special
        print("scipy.special" in sys.modules, f is scipy.special.fdtri)
        """
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.split() == ["True", "True"]
