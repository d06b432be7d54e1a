"""Suite-wide settings and hooks (docs/testing.md: suite time)."""

from __future__ import annotations

import gc
import os
import sys
from collections.abc import Generator

import pytest

# One BLAS thread per test process, as the `imufdi` command runs (imufdi_cli.cli): the suite
# runs two xdist workers on two cores, and numpy's and scipy's OpenBLAS would each add a
# thread per core to every worker; on thin matrices those threads only spin against the
# other worker (tests/detectors 41-46 -> 32-35 s of CPU, pca-parity's 45-dimension
# eigenvalue test 3-4 -> 0.3 s). Set here, when pytest loads this file and before any test
# module imports numpy; xdist workers inherit it from the controller. A value set by the
# user is kept. The outputs are those of the command (and of the split-identical records,
# made with one thread).
THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
for _var in THREAD_VARS:
    os.environ.setdefault(_var, "1")
#: numpy (and so its BLAS) not loaded yet and every cap at one thread: this process's BLAS
#: runs one thread, as the command's does
_ONE_BLAS_THREAD = "numpy" not in sys.modules and all(os.environ[v] == "1" for v in THREAD_VARS)


@pytest.fixture(scope="session")
def one_blas_thread() -> bool:
    """Whether numpy's and scipy's BLAS run one thread in this test process (pinned above
    before numpy was imported; False when a user's value or an earlier import of numpy
    stood in the way). With one thread, products have the bits of the ``imufdi`` command,
    so a test comparing bits with records made that way may run in-process instead of in
    a fresh interpreter."""
    return _ONE_BLAS_THREAD


# No cyclic garbage collection while the test modules are imported and collected: the
# collector kept walking the growing heap of modules, functions and items (about 200 000
# objects, all alive to the end of the session) and took 1.2-1.4 s of the 5.5-7 s of CPU
# of a cold collection (`--collect-only -n 0`, load 7). Reference counting frees what is
# not in a cycle as usual; the cycles made meanwhile are collected once at the end of
# collection (below).
gc.disable()


def _first_use_group(item: pytest.Item) -> int:
    """0 for a test that pays a cost once per process on first use (a Hypothesis test:
    Hypothesis parses the source of every imported ``imufdi_cli`` module for constants to
    try, about 1.4 s of CPU in a fresh process; a test drawing a matplotlib figure: the
    import, about 1 s), 1 for the others."""
    from hypothesis import is_hypothesis_test

    function = getattr(item, "obj", None)
    if function is not None and is_hypothesis_test(function):
        return 0
    if item.get_closest_marker("draws") or item.get_closest_marker("campaign_figure"):
        return 0
    return 1


@pytest.hookimpl(wrapper=True)
def pytest_collection_modifyitems(items: list[pytest.Item]) -> Generator[None, None, None]:
    """Hypothesis tests and figure-drawing tests first, each group otherwise in collection
    order (the same order in every xdist worker, as xdist requires). Work stealing gives
    the first worker the first half of the items and steals from the tail, so these run on
    one worker and the other never pays their first-use costs.

    Hypothesis's constants scan is deferred to that worker. Hypothesis's pytest plugin
    (6.155) scans the source of every imported ``imufdi_cli`` module for constants to try
    in its own ``pytest_collection_modifyitems`` when a Hypothesis test was collected
    (about 1.4 s of CPU in a fresh clone, HypothesisWorks/hypothesis#4627), so every
    worker paid it. While the other implementations of this hook run (this one wraps
    them), the scan returns the constants found so far without scanning; the first
    Hypothesis test's provider calls the same function and scans every module imported by
    then (the scan is incremental: modules imported later are scanned on later calls), so
    the tests draw from the same constants, found once, in the worker that runs them."""
    items[:] = sorted(items, key=_first_use_group)  # sorted() is stable
    try:
        from hypothesis.internal.conjecture import providers
    except ImportError:  # another Hypothesis layout: nothing deferred
        providers = None
    scan = getattr(providers, "_get_local_constants", None)
    if scan is None or not hasattr(providers, "_local_constants"):
        yield
        return
    providers._get_local_constants = lambda: providers._local_constants  # type: ignore[union-attr]
    try:
        yield
    finally:
        providers._get_local_constants = scan  # type: ignore[union-attr]


@pytest.hookimpl(trylast=True)
def pytest_collection_finish(session: pytest.Session) -> None:
    """Collect the cycles collection made (the collector was off, above), then move what
    is left alive (imported modules, collected items: about 200 000 objects) out of the
    garbage collector's sight: they live to the end of the session, so every full
    collection would walk them again for nothing, as would the five collections pytest
    runs at the end of a session to report unraisable exceptions. Then the collector runs
    as usual for the objects the tests make."""
    gc.collect()
    gc.freeze()
    gc.enable()


@pytest.hookimpl(trylast=True)
def pytest_sessionstart(session: pytest.Session) -> None:
    """The xdist controller collects nothing (its workers do) and so never reaches
    :func:`pytest_collection_finish`: it gets its collector back here."""
    if session.config.pluginmanager.has_plugin("dsession"):
        gc.enable()


@pytest.fixture(autouse=True)
def _campaign_figure(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> None:
    """A campaign draws ``detection_probability.png`` at its end (matplotlib, 0.3-0.9 s of
    CPU per campaign), which only the tests marked ``campaign_figure`` look at; the others
    (resume, locks, gates, failures, summaries) get a driver that skips the figure. The
    figure itself is tested in ``campaign/test_plots.py`` and, drawn by the driver, in the
    marked test(s). Campaigns run in a subprocess draw it as usual."""
    if request.node.get_closest_marker("campaign_figure") is not None:
        return
    from imufdi_cli.campaign import driver

    monkeypatch.setattr(driver, "plot_curves", lambda summary, out: None)
